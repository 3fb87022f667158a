"""Synthetic grasp shards for the tests (never shipped as data), and checks of the builder itself.

Objects are small structured tet boxes (optionally tapered), fingers are 2 cm square pads closing along the
object's x axis with a 1 mm gap at first contact. Fields are a smooth deterministic function of the grasp:

    w_f(x) = exp(-|x - p_f|^2 / l^2)                           (p_f: pad centre of finger f, l = 1 cm)
    sigma(x) = F / (2 A_pad) (E / E_0)^0.1 sum_f w_f(x)          [Pa]
    d(x) = 0.1 F / (2 E l) sum_f w_f(x) c_f                      [m]   (c_f: closing direction of finger f)

so a network can learn them from the multigraph. Other test modules import :func:`make_shards`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from defgraspnets.data.grasp_schema import (
    GraspShard,
    GraspShardWriter,
    GripperFingers,
    ObjectRecord,
    shard_file_name,
)
from defgraspnets.fem.mesh import TetMesh

PAD = 0.02
GAP = 1e-3
LENGTH_SCALE = 0.01
MODULI = (2e4, 2e5, 2e6)
F_MAX = 10.0


def pad_fingers(n: int = 3) -> GripperFingers:
    """An n x n vertex square pad in the finger frame's xy plane, closing along +z."""
    xs = np.linspace(-PAD / 2, PAD / 2, n)
    X, Y = np.meshgrid(xs, xs, indexing="ij")
    v = np.stack([X.ravel(), Y.ravel(), np.zeros(n * n)], axis=1)
    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1
            faces += [[a, b, c], [a, c, d]]
    return GripperFingers(v, np.array(faces), np.array([0.0, 0.0, 1.0]))


def box_object(
    name: str,
    size=(0.04, 0.03, 0.03),
    divisions=(4, 3, 3),
    taper: float = 0.0,
    category: str = "cuboid",
    source: str = "primitive",
    moduli=MODULI,
) -> ObjectRecord:
    m = TetMesh.box(size, divisions, origin=tuple(-s / 2 for s in size))
    p = m.points.copy()
    p[:, 1:] *= 1.0 + taper * p[:, :1] / size[0]  # tapered along x (positive Jacobian for |taper| < 1)
    m = TetMesh(p, m.tets, name=name)
    k = len(moduli)
    return ObjectRecord(
        name,
        category,
        source,
        m.points,
        m.tets,
        m.surface_faces,
        np.array(moduli),
        np.full(k, 0.45),
        np.full(k, 1000.0),
    )


def grasp_poses(obj: ObjectRecord, count: int, seed: int):
    """(G, 4, 4) gripper poses, (G, 2, 4, 4) finger contact poses, (G, 2, 3) closing directions."""
    rng = np.random.default_rng(seed)
    half = obj.points[:, 0].max()
    pose, fpose, cdir = [], [], []
    for _ in range(count):
        off = rng.uniform(-0.006, 0.006, size=2)
        theta = rng.uniform(0, np.pi / 2)
        e1 = np.array([0.0, np.cos(theta), np.sin(theta)])
        fingers, dirs = [], []
        for sign in (1.0, -1.0):  # finger 0 at -x closing +x, finger 1 at +x closing -x
            c = np.array([sign, 0.0, 0.0])
            e2 = np.cross(c, e1)
            t = np.eye(4)
            t[:3, :3] = np.stack([e1, e2, c], axis=1)
            t[:3, 3] = [-sign * (half + GAP), off[0], off[1]]
            fingers.append(t)
            dirs.append(c)
        g = np.eye(4)
        g[:3, 3] = [0.0, off[0], off[1] + 0.1]
        pose.append(g)
        fpose.append(fingers)
        cdir.append(dirs)
    return np.array(pose), np.array(fpose), np.array(cdir)


def ramp_fields(obj: ObjectRecord, fpose: np.ndarray, cdir: np.ndarray, E: float, num_steps: int):
    """force (S,), von_mises (S, N), displacement (S, N, 3), finger_travel (S, 2) of one grasp."""
    force = F_MAX * (np.arange(num_steps) + 1) / num_steps
    centres = fpose[:, :3, 3] + GAP * cdir  # pad centres on the object surface
    w = np.exp(-((obj.points[None] - centres[:, None]) ** 2).sum(-1) / LENGTH_SCALE**2)  # (2, N)
    sigma_unit = w.sum(0) / (2 * PAD * PAD) * (E / 2e5) ** 0.1
    d_unit = 0.1 / (2 * E * LENGTH_SCALE) * np.einsum("fn,fc->nc", w, cdir)
    travel_unit = np.full(2, 0.1 / (2 * E * LENGTH_SCALE))
    return (
        force,
        force[:, None] * sigma_unit[None],
        force[:, None, None] * d_unit[None],
        force[:, None] * travel_unit[None],
    )


def write_object(
    out_dir: Path,
    obj: ObjectRecord,
    grasps: int,
    num_steps: int,
    seed: int,
    shards: int = 1,
    failed: tuple = (),
) -> list[Path]:
    """Write ``shards`` shards of ``grasps`` grasps; entries ``(shard, k, g)`` in ``failed`` get status 3."""
    fingers = pad_fingers()
    paths = []
    for i in range(shards):
        pose, fpose, cdir = grasp_poses(obj, grasps, seed * 100 + i)
        w = GraspShardWriter.create(
            out_dir / shard_file_name(obj.name, i, shards),
            obj,
            fingers,
            pose,
            fpose,
            cdir,
            num_steps,
            generator_version="test",
            config="synthetic: true",
        )
        for k, g in w.pending():
            if (i, k, g) in failed:
                nan = np.full
                w.write(
                    k,
                    g,
                    nan(num_steps, np.nan),
                    nan((num_steps, len(obj.points)), np.nan),
                    nan((num_steps, len(obj.points), 3), np.nan),
                    nan((num_steps, 2), np.nan),
                    status=3,
                )
            else:
                w.write(k, g, *ramp_fields(obj, fpose[g], cdir[g], obj.youngs_modulus[k], num_steps))
        paths.append(w.finalize())
    return paths


def make_shards(
    out_dir: Path, grasps: int = 5, num_steps: int = 4, with_real: bool = True, failed: tuple = ((0, 1, 2),)
) -> Path:
    """A small data set: category cuboid (3 objects; cuboid_a in two shards), category slab (2 objects),
    and (optionally) a tapered ``real`` object. Returns ``out_dir``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    objs = [
        (box_object("cuboid_a"), 2),
        (box_object("cuboid_b", size=(0.036, 0.03, 0.032)), 1),
        (box_object("cuboid_c", size=(0.044, 0.028, 0.03)), 1),
        (box_object("slab_a", size=(0.03, 0.04, 0.02), category="slab"), 1),
        (box_object("slab_b", size=(0.032, 0.044, 0.02), category="slab"), 1),
    ]
    if with_real:
        objs.append((box_object("strawberry", taper=0.3, category="fruit", source="real"), 1))
    for i, (obj, n) in enumerate(objs):
        write_object(out_dir, obj, grasps, num_steps, seed=i, shards=n, failed=failed if i == 0 else ())
    return out_dir


def test_synthetic_fields_are_physical(tmp_path):
    obj = box_object("o")
    _, fpose, cdir = grasp_poses(obj, 1, 0)
    force, vm, disp, travel = ramp_fields(obj, fpose[0], cdir[0], 2e5, 4)
    assert np.all(np.diff(force) > 0) and force[-1] == pytest.approx(F_MAX)
    assert np.all(vm >= 0) and vm.max() > 1e3
    # displacement scales as 1/E and pushes the -x side towards +x
    _, _, disp_stiff, _ = ramp_fields(obj, fpose[0], cdir[0], 2e6, 4)
    np.testing.assert_allclose(disp_stiff * 10, disp, rtol=1e-12)
    left = obj.points[:, 0] < -0.015
    assert np.all(disp[-1, left, 0] > 0)


def test_make_shards_writes_valid_files(tmp_path):
    make_shards(tmp_path, grasps=3, num_steps=2)
    names = sorted(p.name for p in tmp_path.glob("*.h5"))
    assert "cuboid_a__shard0of2.h5" in names and "cuboid_a__shard1of2.h5" in names
    shard = GraspShard(tmp_path / "cuboid_a__shard0of2.h5")
    assert shard.status[1, 2] == 3 and (shard.status == 0).sum() == 3 * 3 - 1
    assert not list(tmp_path.glob("*.partial.h5"))
