"""The wrench CNN of thesis §3.4: depth image of the membrane -> 6-D wrench.

Thesis: "Each point cloud input, an array of depth measurements, is passed through a series of two
convolutional and max-pooling layers, and then through a fully-connected regression network to
yield the predicted resultant force-torque measurement"; dropout 0.2 in the fully connected layers;
input 171 x 224. Fig. 3.6 (layer widths, kernel sizes) is not in the text, so these are choices:

    x (B, 1, H, W)                                  normalized depth change (data.tactile_datamodule)
    [avg-pool s_in]                                 optional input downsampling (default none)
    conv k x k (1 -> C1) + ReLU + max-pool p
    conv k x k (C1 -> C2) + ReLU + max-pool p       (padding k // 2 keeps the size before pooling)
    flatten -> [linear + ReLU + dropout 0.2] x len(hidden) -> linear -> (B, 6)

Defaults C = (16, 32), k = 5, p = 4, hidden = (128,): at 171 x 224 the feature map is
32 x 10 x 14 and the network has ~0.6 M parameters (p = 2 would give ~10 M, mostly in the first
linear layer). Output order: (F_x, F_y, F_z [N], tau_x, tau_y, tau_z [N m]) in the sensor frame.
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["WrenchCNN"]


class WrenchCNN(nn.Module):
    """Two conv + max-pool stages and a fully connected regression head with dropout.

    Args:
        image_shape: (H, W) of the input images (thesis: (171, 224)).
        channels: output channels of the two convolutions.
        kernel_size: convolution kernel size (odd).
        pool_size: max-pool size and stride after each convolution.
        hidden_features: widths of the hidden fully connected layers.
        dropout: dropout probability after each hidden layer (thesis: 0.2).
        input_pool: average-pooling factor applied to the input first (1: full resolution).
        out_features: 6 (force then torque).
    """

    def __init__(
        self,
        image_shape: tuple[int, int] = (171, 224),
        channels: tuple[int, int] = (16, 32),
        kernel_size: int = 5,
        pool_size: int = 4,
        hidden_features: tuple[int, ...] = (128,),
        dropout: float = 0.2,
        input_pool: int = 1,
        out_features: int = 6,
    ):
        super().__init__()
        # constructor arguments, stored in checkpoints so that a trained network rebuilds from the file
        self.config = {
            "image_shape": [int(s) for s in image_shape],
            "channels": [int(c) for c in channels],
            "kernel_size": int(kernel_size),
            "pool_size": int(pool_size),
            "hidden_features": [int(h) for h in hidden_features],
            "dropout": float(dropout),
            "input_pool": int(input_pool),
            "out_features": int(out_features),
        }
        self.image_shape = tuple(int(s) for s in image_shape)
        if len(self.image_shape) != 2 or min(self.image_shape) < 1:
            raise ValueError(f"image_shape must be (H, W) with positive sizes, got {image_shape!r}")
        if len(channels) != 2:
            raise ValueError(f"the thesis network has two convolutions; got channels={channels!r}")
        if kernel_size % 2 != 1:
            raise ValueError(f"kernel_size must be odd, got {kernel_size}")
        if not 0.0 <= dropout < 1.0:
            raise ValueError(f"dropout must be in [0, 1), got {dropout}")
        layers: list[nn.Module] = [nn.AvgPool2d(input_pool)] if input_pool > 1 else []
        c_in = 1
        for c_out in channels:
            layers += [
                nn.Conv2d(c_in, int(c_out), kernel_size, padding=kernel_size // 2),
                nn.ReLU(),
                nn.MaxPool2d(pool_size),
            ]
            c_in = int(c_out)
        self.features = nn.Sequential(*layers)
        try:
            with torch.no_grad():
                n_flat = self.features(torch.zeros(1, 1, *self.image_shape)).numel()
        except RuntimeError as e:  # a pooling window larger than its input
            n_flat = 0
            cause = e
        else:
            cause = None
        if n_flat == 0:
            raise ValueError(
                f"image_shape {self.image_shape} is too small for pooling {input_pool} x {pool_size}^2"
            ) from cause
        head: list[nn.Module] = [nn.Flatten()]
        width = n_flat
        for h in hidden_features:
            head += [nn.Linear(width, int(h)), nn.ReLU(), nn.Dropout(dropout)]
            width = int(h)
        head.append(nn.Linear(width, out_features))
        self.head = nn.Sequential(*head)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 1, H, W) normalized depth change -> (B, 6) wrench [N, N m]."""
        if x.ndim != 4 or x.shape[1] != 1 or tuple(x.shape[-2:]) != self.image_shape:
            raise ValueError(
                f"WrenchCNN expects input of shape (B, 1, {self.image_shape[0]}, {self.image_shape[1]}), "
                f"got {tuple(x.shape)}"
            )
        return self.head(self.features(x))
