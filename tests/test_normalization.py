"""Target scaling of DefGraspNets (defgraspnets.data.normalization) and the displacement target saved with
the model. The scaling is invertible, frame-independent, and with
the modulus saturation the rigid motion of a stiff object is not amplified."""

import math

import pytest
import torch

from defgraspnets.data.normalization import TargetScaling
from defgraspnets.models.defgraspnets_module import DefGraspNetsModule


def _random_rotation(gen: torch.Generator) -> torch.Tensor:
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r))
    return q if torch.det(q) > 0 else -q


@pytest.mark.parametrize("saturation", [None, 1e6])
def test_displacement_scaling_round_trip_and_rotation(saturation):
    gen = torch.Generator().manual_seed(0)
    scaling = TargetScaling(modulus_reference=1e6, modulus_saturation=saturation)
    d = 1e-3 * torch.randn(50, 3, generator=gen, dtype=torch.float64)
    e = 10 ** (4 + 5 * torch.rand(50, generator=gen, dtype=torch.float64))  # 1e4 .. 1e9 Pa
    y = scaling.displacement_to_target(d, e)
    torch.testing.assert_close(scaling.displacement_from_target(y, e), d, rtol=1e-12, atol=0)
    rot = _random_rotation(gen)  # scaling a vector field must commute with rotating the object frame
    torch.testing.assert_close(
        scaling.displacement_to_target(d @ rot.T, e), y @ rot.T, rtol=1e-12, atol=1e-18
    )


def test_displacement_scaling_limits():
    d = torch.tensor([[1e-3, -2e-3, 5e-4]], dtype=torch.float64)
    plain = TargetScaling(modulus_reference=1e6)
    for e in (3e5, 1e7):
        et = torch.tensor([e], dtype=torch.float64)
        torch.testing.assert_close(plain.displacement_to_target(d, et), d * e / 1e6)
    sat = TargetScaling(modulus_reference=1e6, modulus_saturation=1e6)
    factor = lambda e: sat.displacement_factor(torch.tensor([e], dtype=torch.float64)).item()  # noqa: E731
    assert factor(1e6) == pytest.approx(0.5, rel=1e-12)
    # far below E_sat: d E / E_ref (the 1/E elastic scaling); far above: E-independent, E_sat / E_ref
    assert factor(1e2) == pytest.approx(1e-4, rel=1e-3)
    assert factor(1e10) == pytest.approx(1.0, rel=1e-3)
    # the 33x spread of plain factors over E = 0.3..10 MPa shrinks to about 4x
    assert factor(1e7) / factor(3e5) == pytest.approx((10 / 11) / (0.3 / 1.3), rel=1e-12)
    assert factor(1e7) / factor(3e5) < 4.0


@pytest.mark.parametrize("bad", [0.0, -1e6, math.inf, math.nan])
def test_modulus_saturation_rejects_non_positive(bad):
    with pytest.raises(ValueError, match="modulus_saturation"):
        TargetScaling(modulus_saturation=bad)


def test_checkpoint_without_saturation_keeps_plain_scaling(tmp_path):
    """A checkpoint saved before modulus_saturation existed loads with the scaling it was trained with."""
    module = DefGraspNetsModule(latent=8, num_blocks=1, modulus_saturation=2e6)
    assert module.net.scaling.modulus_saturation == 2e6
    ckpt = {"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams)}
    ckpt["hyper_parameters"].pop("modulus_saturation")
    ckpt["pytorch-lightning_version"] = "2.0.0"
    path = tmp_path / "old.ckpt"
    torch.save(ckpt, path)
    old = DefGraspNetsModule.load_from_checkpoint(path, map_location="cpu")
    assert old.net.scaling.modulus_saturation is None


def test_displacement_target_travels_with_the_checkpoint():
    module = DefGraspNetsModule(latent=8, num_blocks=1)
    assert module.displacement_target == "total"
    module._displacement_target = "rigid_removed"
    ckpt: dict = {}
    module.on_save_checkpoint(ckpt)
    loaded = DefGraspNetsModule(latent=8, num_blocks=1)
    loaded.on_load_checkpoint(ckpt)
    assert loaded.displacement_target == "rigid_removed"
    older = DefGraspNetsModule(latent=8, num_blocks=1)
    older.on_load_checkpoint({})  # saved before the choice existed: trained on the total field
    assert older.displacement_target == "total"
    resumed = DefGraspNetsModule(latent=8, num_blocks=1)
    resumed._displacement_target = "total"  # what setup() took from data.displacement when resuming
    with pytest.raises(ValueError, match="data.displacement=total differs from the 'rigid_removed'"):
        resumed.on_load_checkpoint(ckpt)
