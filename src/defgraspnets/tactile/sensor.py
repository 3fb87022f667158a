"""The soft tactile sensor simulated with the FEM engine: inflation, indentation, depth image, wrench.

The Ecoflex membrane (:mod:`defgraspnets.tactile.membrane`, clamped at its rim) is loaded by the gas
inside the sensor and touched by one rigid indenter; every reading is a quasi-static equilibrium of

    Pi(u, t) = U_elastic(u) + contact(u, t) - G(V(u)),

solved by :class:`defgraspnets.fem.QuasiStaticSolver` for B indentations at once (see
:mod:`defgraspnets.fem.pressure` for the gas potential G). The gas fills the membrane cavity
V (inner surface closed by the rim disk) and the rigid housing V_h below the rim:

- **open** capsule (regulator / free air exchange): the gauge pressure p = P - P_atm is fixed;
- **closed** capsule (the sealed sensor): isothermal ideal gas, P (V + V_h) = PV fixed (Boyle), so
  p(V) = PV / (V + V_h) - P_atm rises as an indenter squeezes the cavity: the closed sensor is stiffer.

A :class:`~defgraspnets.tactile.membrane.PVState` (P, V) names the gas state: open uses its gauge
pressure P - P_atm, closed its product PV (the membrane then inflates until P (V + V_h) = PV).

Indentation: the indenter moves rigidly along a unit direction d. Its depth is measured from first
contact with the *inflated* membrane (the onset travel is found from the indenter's signed distance to
the inflated outer surface), and it is displacement-controlled by the solver with Coulomb friction mu.
Each :mod:`~defgraspnets.tactile.indenters` type is one FEM rigid shape, defined in the indenter's own
local frame (:func:`fem_shape`):

- :class:`SphereIndenter` -> ``fem.Sphere``, any direction;
- :class:`CapsuleIndenter` (axis local x) -> ``fem.Capsule`` along x, directions perpendicular to its axis;
- :class:`BoxIndenter` (prism) -> sharp ``fem.RoundedBox`` (radius 0), pressed along its local +-z (a face
  first);
- :class:`RingIndenter` -> closed ``fem.TriangleMesh`` of its 64-sided annulus, pressed along its local
  +-z (the annular face first).

Sub-vertex contact (``MembraneSimulator(contact_subdivisions=n)``, ``SolverOptions.contact_subdivisions``;
off, n = 1, by default). The FEM contact is between the indenter and contact points of the membrane's
surface: by default its vertices, ~9-10 mm apart on the coarse (cap 8) membrane, so the thesis's 1 cm
fingertip (r = 5 mm) aimed between them passes through the triangles (no onset at the midpoint of an
edge at the pole; contact lost past 5 mm at a triangle's centroid). With n > 1 the points are the grid of
the n-subdivision of every surface triangle (see :mod:`defgraspnets.fem.contact`), and the onset is found
from the contact points on the outer surface. Measured (``benchmarks/fem_triangle_contact_cpu.md``, 2-core
CPU, sealed at 1.5 kPa, radial pokes 5-25 mm at the pole, a vertex, an edge midpoint and a centroid): with
n = 2 or 3 every landing point converges at every depth, at 2-4x the vertex contact's Newton iterations
and time per path (cap 8, n = 3: 629 Newton iterations, 12 s for the four paths; the cap-16 membrane with
vertex contact: 1189, 148 s). But the force then still depends on where the fingertip lands: 32-41 % apart
at 5 mm, 9-13 % at 25 mm (cap 16: 11 % and 4 %), and the coarse membrane stays 28-93 % stiffer than the
cap-16 one. Neither is contact: the 20 mm sphere with vertex contact shows the same landing dependence on
cap 8 (an edge midpoint 1.58 x the pole's force at 5 mm): the FEM field is linear across each 9-10 mm face,
so a load narrower than a face landing between its vertices is spread over them and meets a stiffer
surface than at a vertex (4 layers through the thickness instead of 2 change the forces by < 3 %).
Sub-vertex contact removes the slipping through, not the coarse mesh's bias; the cap-16 membrane remains
the reference for the fingertip (within -8..+7 % of the cap-24 membrane with n = 2, whose curves agree
over the four landing points to 1-4 %; cap 8 with n = 3 lies 21-86 % above it).

The FEM body's local z must be its travel axis, so its frame is the indenter's pose frame turned by a
symmetry Q of the shape that maps local z onto the direction (:meth:`MembraneSimulator._body_frame`);
such a Q exists exactly for the directions listed.

Wrenches (sensor frame, about the sensor origin, SI): with s_i the clamp's support force on rim vertex
i, f_i the gas force on vertex i and F_c the force the membrane exerts on the indenter,

    membrane equilibrium:      sum_i s_i + sum_i f_i - F_c = 0,
    gas resultant on membrane: sum_i f_i = p A_rim e_z      (A_rim: area enclosed by the rim loop),

so the clamp reactions alone carry the gas's lift p A_rim besides the contact force. The gas presses
on the housing with the opposite resultant (a uniformly pressurized closed container feels no net
force or torque), so the wrench the base transmits to the robot flange, i.e. what the thesis's wrist
F/T sensor reads,

    F_base = -sum_i s_i - sum_i f_i = -F_c,
    T_base = -sum_i x_i x (s_i + f_i) = -(torque of F_c about the origin),

is the indenter's contact wrench with the opposite sign, independent of the gas pressure.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, fields, replace

import numpy as np
from scipy.spatial.transform import Rotation

from defgraspnets import fem
from defgraspnets.tactile.camera import PICO_FLEXX, CameraIntrinsics, DepthCamera, DepthFrame
from defgraspnets.tactile.indenters import (
    BoxIndenter,
    CapsuleIndenter,
    Indenter,
    IndenterError,
    Pose,
    RingIndenter,
    SphereIndenter,
    WorkspaceError,
    check_workspace,
)
from defgraspnets.tactile.membrane import ATMOSPHERIC_PRESSURE, MembraneError, MembraneSensor, PVState


def exact_linear_solver(device) -> str:
    """The exact linear solver of the membrane on ``device``: block-tridiagonal Cholesky on the CPU
    (the thin shell's breadth-first levels are narrow rings; 2-core CPU, 8 poke paths of the default
    benchmark: 229 s against 317 s with SuperLU, a pole poke on the 3747-vertex membrane 18 s against
    38 s, the same wrenches), and on the GPU ``dense_banded``: the batched block-tridiagonal Cholesky
    when at least ``SolverOptions.banded_min_problems`` (4) problems need a factorization, one dense
    Cholesky per problem when fewer do (the banded solver's fixed cost per call is ~3x a dense
    factorization's on small batches). Measured on one
    H100 (192 poke paths of the grid, cap 8, 20 mm sphere, 960 states): in batches of 64 paths 264.0 s
    dense, 229.9 s banded; streamed through 64 problems (:meth:`MembraneSimulator.indent_stream`, the
    batch stays full) 232.9 s dense, 164.8 s banded. (Before the load steps ran without a barrier, in
    lockstep, dense and banded tied: 102.1 and 104.4 s for 64 paths.) Streamed through 128 problems, on
    another lease: banded 145.8 s, ``dense_banded`` 127.8 s (its switch point comes from the FEM box,
    ``benchmark_fem.py``; a few paths' tails then factor densely). The whole 10,000-state grid streamed
    through 128 problems (session 34, before indefinite exact Hessians were damped instead of LU-solved):
    671 s, 59 readings failed (``benchmarks/tactile_poke_cuda_full_grid_h100_s34.json``)."""
    import warp as wp

    wp.init()
    return "dense_banded" if wp.get_device(device).is_cuda else "banded"


def membrane_solver_options(device=None, **overrides) -> fem.SolverOptions:
    """The FEM options of :class:`MembraneSimulator` on ``device``; ``overrides`` replace any
    :class:`~defgraspnets.fem.SolverOptions` field (None: keep the default), checked as SolverOptions
    checks them.

    - the exact linear solver of the device (:func:`exact_linear_solver`);
    - rtol 1e-5: where the indenter dimples the membrane, compressed elements get a PSD-projected
      Hessian and Newton converges only linearly, so the engine's default 1e-7 costs many iterations;
    - contact_smoothing 1e-2: the penalty's onset is C2 over 1 % of the local element size (the
      indenter's contact pressure then penetrates 0.5 % of an element more, ~45 um on the coarse
      membrane). With the plain C1 penalty, membrane vertices grazing the rim of a sliding contact
      patch switch the Hessian on and off and tilted pokes crawl for hundreds of Newton iterations.
      Measured on 32 poke paths of the grid (every 61st; 20 mm sphere, cap 8, sealed at 1.5 kPa,
      one H100): 160 -> 65 s, 6084 -> 2125 lockstep Newton iterations, 1 -> 0 failed readings; base
      forces moved by a median 0.14 % (90th percentile 0.34 %), except 3 of 164 readings of pokes
      tilted 50-80 degrees, whose sphere slides: by 0.4-0.7 N of 1.9-4.4 N (another friction path).
    """
    options = {"linear_solver": exact_linear_solver(device), "rtol": 1e-5, "contact_smoothing": 1e-2}
    known = {f.name for f in fields(fem.SolverOptions)}
    unknown = sorted(set(overrides) - known)
    if unknown:
        raise TypeError(f"unknown FEM solver option(s) {unknown}; SolverOptions has {sorted(known)}")
    options.update({k: v for k, v in overrides.items() if v is not None})
    return fem.SolverOptions(**options)


__all__ = [
    "SUPPORTED_INDENTERS",
    "membrane_solver_options",
    "Indentation",
    "MembraneSimulator",
    "TactileReading",
    "fem_shape",
    "half_width",
]

_FAR = 10.0  # m: where idle indenters wait (never touching the membrane)

#: the indenter types the FEM sensor simulates (:func:`fem_shape`)
SUPPORTED_INDENTERS = (SphereIndenter, CapsuleIndenter, BoxIndenter, RingIndenter)


def _check_supported(indenter) -> None:
    if not isinstance(indenter, SUPPORTED_INDENTERS):
        names = ", ".join(cls.__name__ for cls in SUPPORTED_INDENTERS)
        raise IndenterError(f"the FEM sensor supports {names}, got {type(indenter).__name__}")


def fem_shape(indenter: Indenter):
    """The FEM rigid shape of ``indenter`` in the indenter's own local frame (module docstring).

    The ring is its ``local_trimesh`` (64-sided annulus): its surface lies within
    R_o (1 - cos(pi / 64)) (18 um for R_o = 15 mm) of the analytic ring's.

    Raises:
        IndenterError: not one of :data:`SUPPORTED_INDENTERS`.
    """
    _check_supported(indenter)
    if isinstance(indenter, SphereIndenter):
        return fem.Sphere(indenter.radius)
    if isinstance(indenter, CapsuleIndenter):
        return fem.Capsule(indenter.radius, 0.5 * indenter.length, direction=(1.0, 0.0, 0.0))
    if isinstance(indenter, BoxIndenter):
        return fem.RoundedBox(tuple(indenter.half_extents), radius=0.0)
    mesh = indenter.local_trimesh()
    return fem.TriangleMesh(np.asarray(mesh.vertices), np.asarray(mesh.faces))


def half_width(indenter: Indenter) -> float:
    """Radius [m] of the largest ball inside ``indenter`` (half its thinnest width): sphere and capsule R,
    box half its shortest edge, ring half the thinner of wall and height."""
    _check_supported(indenter)
    if isinstance(indenter, (SphereIndenter, CapsuleIndenter)):
        return float(indenter.radius)
    if isinstance(indenter, BoxIndenter):
        return 0.5 * float(min(indenter.size_x, indenter.size_y, indenter.size_z))
    return 0.5 * float(min(indenter.outer_radius - indenter.inner_radius, indenter.height))


@dataclass(frozen=True)
class Indentation:
    """One indentation: the indenter's pose at the start (any pose from which it moves towards the
    membrane along ``direction``), the unit ``direction`` in the sensor frame, and the ``depth`` [m]
    it travels beyond first contact with the inflated membrane."""

    pose: Pose
    depth: float
    direction: tuple = (0.0, 0.0, -1.0)

    def __post_init__(self):
        if not isinstance(self.pose, Pose):
            raise IndenterError(f"Indentation.pose must be a Pose, got {type(self.pose).__name__}")
        if not (np.isscalar(self.depth) and np.isfinite(self.depth) and self.depth >= 0):
            raise IndenterError(f"indentation depth must be a finite number >= 0 m, got {self.depth!r}")
        d = np.asarray(self.direction, dtype=np.float64)
        if d.shape != (3,) or not np.all(np.isfinite(d)) or np.linalg.norm(d) < 1e-12:
            raise IndenterError(
                f"indentation direction must be a finite non-zero (3,) vector, got {self.direction!r}"
            )
        object.__setattr__(self, "direction", tuple(d / np.linalg.norm(d)))


@dataclass
class TactileReading:
    """One simulated sensor reading (sensor frame, SI units).

    Attributes:
        positions: (N, 3) deformed membrane vertex positions [m].
        depth: the interior camera's frame of the deformed inner surface (None if not rendered).
        contact_force: (3,) force the membrane exerts on the indenter [N].
        base_wrench: (6,) force and torque the sensor base transmits to the flange, about the sensor
            origin [N, N m]; equals minus the indenter's contact wrench (module docstring).
        rim_force: (3,) force the membrane exerts on the clamp (clamp reactions only) [N]; differs from
            the base force by the gas's lift p A_rim e_z.
        gauge_pressure: gas gauge pressure p [Pa].
        gas_volume: gas volume V + V_h [m^3].
        depth_travel: indentation depth beyond first contact [m].
        indenter_position: (3,) indenter origin at the reading [m].
        indenter_pose: the indenter's pose at the reading (its origin and orientation, sensor frame).
        converged: whether the equilibrium solve succeeded (if not, nothing else is an answer).
        solve_time: wall time of the batched solve that produced it [s].
    """

    positions: np.ndarray
    depth: DepthFrame | None
    contact_force: np.ndarray
    base_wrench: np.ndarray
    rim_force: np.ndarray
    gauge_pressure: float
    gas_volume: float
    depth_travel: float
    indenter_position: np.ndarray
    indenter_pose: Pose
    converged: bool
    solve_time: float


class MembraneSimulator:
    """Quasi-static simulation of the membrane sensor under gas pressure and one rigid indenter.

    Args:
        sensor: the membrane (:func:`~defgraspnets.tactile.membrane.build_membrane`; a coarse mesh, e.g.
            ``cap_divisions=8, layers=2``, solves in seconds on a CPU).
        indenter: a :class:`SphereIndenter`, :class:`CapsuleIndenter`, :class:`BoxIndenter` or
            :class:`RingIndenter` (its geometry; poses come with each :class:`Indentation`, whose direction
            must suit the shape: module docstring).
        gas: the gas state (:class:`PVState`) and ``closed``: sealed capsule (isothermal, PV constant)
            or open (gauge pressure fixed).
        batch_size: B indentations solved together.
        friction: Coulomb coefficient between indenter and membrane.
        intrinsics: the interior camera (default: the pico flexx, 224 x 171); None renders no image.
        options: FEM :class:`~defgraspnets.fem.SolverOptions` (default: :func:`membrane_solver_options`).
        inflation_steps: load steps of the inflation.
        device: Warp device of the solver and the camera ("cpu", "cuda", ...); None = Warp's default.
        contact_subdivisions: n, sub-vertex contact (``SolverOptions.contact_subdivisions``, replaces the
            options' value when given): the indenter touches the grid points of the n-subdivision of every
            membrane surface triangle instead of its vertices alone, so an indenter narrower than the
            vertex spacing (the 1 cm fingertip on the cap-8 membrane, vertices ~9-10 mm apart) no longer
            slips between the vertices. None: the options' value (1, vertex contact, by default). Measured
            in ``benchmarks/fem_triangle_contact_cpu.md`` (module docstring).

    The membrane is inflated on construction (:attr:`reference`).
    """

    def __init__(
        self,
        sensor: MembraneSensor,
        indenter: Indenter,
        gas: PVState,
        closed: bool = False,
        batch_size: int = 1,
        friction: float = 0.5,
        intrinsics: CameraIntrinsics | None = PICO_FLEXX,
        options: fem.SolverOptions | None = None,
        inflation_steps: int = 2,
        device: str | None = None,
        contact_subdivisions: int | None = None,
    ):
        if not isinstance(sensor, MembraneSensor):
            raise TypeError(f"sensor must be a MembraneSensor, got {type(sensor).__name__}")
        if not isinstance(gas, PVState):
            raise TypeError(f"gas must be a PVState, got {type(gas).__name__}")
        shape = fem_shape(indenter)  # raises IndenterError for unsupported types
        if (
            friction is None
            or isinstance(friction, (str, bytes))
            or not (np.isfinite(friction) and friction >= 0)
        ):
            raise ValueError(f"friction must be finite and >= 0, got {friction!r}")
        self.sensor = sensor
        self.indenter = indenter
        self._half_width = half_width(indenter)
        self.gas = gas
        self.closed = bool(closed)
        self.batch_size = int(batch_size)
        dims = sensor.dimensions
        body = fem.RigidBody(
            "indenter", shape, control=fem.Control.displacement((0.0, 0.0, 1.0)), friction=float(friction)
        )

        options = options or membrane_solver_options(device)
        if contact_subdivisions is not None:
            options = replace(options, contact_subdivisions=contact_subdivisions)

        def build_solver(batch_size: int) -> fem.QuasiStaticSolver:
            return fem.QuasiStaticSolver(
                sensor.mesh,
                [body],
                sensor.material,
                batch_size=batch_size,
                device=device,
                fixed=sensor.clamped_vertices,
                options=options,
                pressure_surface=fem.PressureSurface(
                    sensor.inner_faces, sensor.rim_center, external_volume=dims.housing_volume
                ),
            )

        self._build_solver = build_solver
        self._inflated_template: fem.QuasiStaticSolver | None = None  # one inflated problem (indent_stream)
        self.solver = build_solver(self.batch_size)
        # the camera ray-casts on the solver's device (the deformed surface is already there)
        self.camera = None if intrinsics is None else DepthCamera(intrinsics, device=self.solver.device)
        self._inflation_steps = int(inflation_steps)
        ring = sensor.mesh.points[sensor.rim_loop]
        ring = ring[np.argsort(np.arctan2(ring[:, 1], ring[:, 0]))] - sensor.rim_center
        #: area enclosed by the rim loop [m^2] (the gas lifts the membrane with p times it)
        self.rim_area = float(0.5 * np.cross(ring, np.roll(ring, -1, axis=0)).sum(axis=0)[2])
        self.reference = self._inflate()

    # ------------------------------------------------------------------ gas
    @property
    def pressure_load(self) -> fem.PressureLoad:
        """The FEM gas law of :attr:`gas`: fixed gauge pressure (open) or P (V + V_h) = PV (closed)."""
        if self.closed:
            return fem.PressureLoad.isothermal(self.gas.pv, ambient_pressure=ATMOSPHERIC_PRESSURE)
        return fem.PressureLoad.fixed(self.gas.gauge_pressure)

    def _idle_poses(self) -> np.ndarray:
        T = np.broadcast_to(np.eye(4), (self.batch_size, 4, 4)).copy()
        T[:, 2, 3] = _FAR
        return T

    def _inflate(self) -> TactileReading:
        """Inflate from the neutral (free-air) membrane to the gas state, indenters far away."""
        t0 = time.perf_counter()
        eq = self._inflate_solver(self.solver)
        #: the FEM equilibrium of the inflated membrane (all problems)
        self.inflated = eq
        idle = self._idle_poses()
        return self._readings(
            eq, np.zeros(self.batch_size), idle, idle[:, :3, :3], time.perf_counter() - t0, 1
        )[0]

    def _inflate_solver(self, s: fem.QuasiStaticSolver) -> fem.Equilibrium:
        """Inflate the problems of ``s`` from the neutral membrane to the gas state, indenters far away."""
        s.reset()
        s.set_body_pose("indenter", self._idle_poses()[: s.batch_size])
        law = self.pressure_load.arrays(s.batch_size)
        for k in range(1, self._inflation_steps + 1):
            frac = k / self._inflation_steps
            eq = s.solve(
                targets={"indenter": 0.0},
                pressure=fem.PressureLoad(gauge_pressure=frac * law[:, 0], pv=frac * law[:, 1]),
            )
        if not eq.converged.all():
            raise MembraneError(
                f"inflation to {self.gas!r} ({'closed' if self.closed else 'open'}) did not converge: "
                f"{fem.SolveStatus(int(eq.status[0])).name}"
            )
        return eq

    def _template(self) -> fem.QuasiStaticSolver:
        """One problem inflated exactly as each problem of :attr:`solver` was (built on first use)."""
        if self._inflated_template is None:
            template = self._build_solver(1)
            self._inflate_solver(template)
            self._inflated_template = template
        return self._inflated_template

    # ------------------------------------------------------------------ indentation geometry
    def onset_travel(self, indentation: Indentation, indenter: Indenter | None = None) -> float:
        """Travel [m] along the direction at which the indenter (default: the simulator's; ``indenter``: one
        of its shape with other dimensions) first touches the inflated membrane.

        Root of m(t) = min over outer vertices of the indenter's signed distance when moved by t d
        (negative: it already penetrates at its start pose, and backs off). Works for every supported
        shape: it only needs the indenter's signed distance and its :func:`half_width`. Vectorized, in the
        indenter's frame: the march evaluates 32 travels at a time, then each round evaluates 32 travels
        inside the bracket (which shrinks 33x per round; 10 rounds narrow it as far as a 50-step bisection).

        Raises:
            WorkspaceError: the indenter is not clear of the membrane even 4 R_o back, or never touches it.
        """
        indenter = self.indenter if indenter is None else indenter
        body = indenter.with_pose(indentation.pose)
        x = body.pose.inverse_apply(self.outer_contact_points())
        d = np.asarray(indentation.direction)
        d_local = body.pose.rotation.inv().apply(d)

        def first_touch(t: np.ndarray) -> int:
            """Index of the first travel of ``t`` at which the bodies touch (len(t): none)."""
            gap = body.local_signed_distance((x[None] - t[:, None, None] * d_local).reshape(-1, 3))
            return int(np.argmax(np.append(gap.reshape(len(t), -1).min(axis=1) <= 0, True)))

        # march from well outside in steps shorter than half the membrane's thickness and half the
        # indenter's thinnest width (so neither passes through the other unseen), then narrow the first
        # bracket
        dims = self.sensor.dimensions
        step = 0.5 * min(
            dims.thickness, self._half_width if indenter is self.indenter else half_width(indenter)
        )
        span = 4.0 * dims.outer_radius
        if first_touch(np.array([-span])) == 0:
            raise WorkspaceError(f"the indenter at {indentation.pose!r} is not clear of the membrane")
        march = np.arange(-span + step, span + step, step)
        k = len(march)
        for begin in range(0, len(march), 32):
            k = begin + first_touch(march[begin : begin + 32])
            if k < min(begin + 32, len(march)):
                break
        if k == len(march):
            raise WorkspaceError(
                f"the indenter at {indentation.pose!r} moving along {d.tolist()} never touches the membrane"
            )
        lo, hi = (march[k - 1] if k else -span), march[k]
        for _ in range(10):  # 33^10 > 2^50
            inner = lo + (hi - lo) * np.arange(1, 33) / 33.0
            k = first_touch(inner)
            lo, hi = (inner[k - 1] if k else lo), (inner[k] if k < len(inner) else hi)
        return 0.5 * (lo + hi)

    def outer_contact_points(self, positions: np.ndarray | None = None) -> np.ndarray:
        """(P_o, 3) the membrane's contact points on its outer surface at vertex ``positions`` (V, 3) [m]
        (default: the inflated state): the outer vertices, and with sub-vertex contact
        (``contact_subdivisions`` > 1) the solver's points on the outer triangles too, so that the onset of
        an indentation is where the indenter first touches a contact point (a small indenter landing
        between the vertices touches the triangle's points first)."""
        positions = self.inflated.positions[0] if positions is None else np.asarray(positions)
        solver = self.solver
        if solver.options.contact_subdivisions == 1:
            return positions[self.sensor.outer_vertices]
        outer = np.zeros(len(positions), dtype=bool)
        outer[self.sensor.outer_vertices] = True
        vertices, weights = solver.contact_point_vertices, solver.contact_point_weights
        on_outer = outer[vertices].all(axis=1)
        return np.einsum("pij,pi->pj", positions[vertices[on_outer]], weights[on_outer])

    def _body_frame(self, indentation: Indentation) -> np.ndarray:
        """4x4 pose of the FEM body whose local z is the indentation direction (travel axis).

        The FEM shape is the indenter's in its local frame (:func:`fem_shape`), so the body frame is the
        pose's rotation R turned by a symmetry Q of the shape with R Q e_z = d: any rotation for the
        sphere, a turn about the axis for the capsule (d perpendicular to it), and for the box and the
        ring Q = I (d = local +z) or the half turn about local x, diag(1, -1, -1) (d = local -z).

        Raises:
            IndenterError: no such symmetry (e.g. a box pressed along its local x, a tilted ring).
        """
        d = np.asarray(indentation.direction)
        if isinstance(self.indenter, SphereIndenter):
            return fem.bodies.frame_from_z(indentation.pose.position, d)
        T = np.eye(4)
        T[:3, 3] = indentation.pose.position
        if isinstance(self.indenter, CapsuleIndenter):
            a = indentation.pose.rotation.apply([1.0, 0.0, 0.0])  # capsule axis in the sensor frame
            if abs(np.dot(a, d)) > 1e-6:
                raise IndenterError("a capsule indents perpendicular to its axis (its local x)")
            T[:3, 0], T[:3, 1], T[:3, 2] = a, np.cross(d, a), d
            return T
        R = indentation.pose.rotation.as_matrix()
        along = float(R[:, 2] @ d)  # box and ring: d must be their local +-z
        if np.linalg.norm(d - along * R[:, 2]) > 1e-6:
            raise IndenterError(
                f"a {self.indenter.kind} indenter presses along its local z axis (a flat face first); "
                f"the direction {d.tolist()} is {np.degrees(np.arccos(min(1.0, abs(along)))):.3g} deg off it"
            )
        T[:3, :3] = R if along > 0 else R @ np.diag([1.0, -1.0, -1.0])
        return T

    # ------------------------------------------------------------------ indentation
    def _prepare(self, indentations) -> tuple[list[Indentation], np.ndarray, np.ndarray]:
        """Checked items, FEM body frames at contact onset (B, 4, 4) and indenter rotations (B, 3, 3)."""
        items = list(indentations)
        if not 1 <= len(items) <= self.batch_size:
            raise ValueError(f"give 1 to {self.batch_size} indentations, got {len(items)}")
        for item in items:
            if not isinstance(item, Indentation):
                raise TypeError(f"indentations must be Indentation instances, got {type(item).__name__}")
        frames = self._idle_poses()
        rotations = np.broadcast_to(np.eye(3), (self.batch_size, 3, 3)).copy()
        for b, item in enumerate(items):
            frames[b], rotations[b] = self.path_frame(item)
        return items, frames, rotations

    def path_frame(
        self, item: Indentation, indenter: Indenter | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """The FEM body frame (4, 4) of an indentation at contact onset and the indenter's rotation (3, 3)
        (``indenter``: as :meth:`onset_travel`).

        Raises:
            WorkspaceError: the indenter would reach below the clamped rim plane, or never meets the
                membrane; IndenterError: the direction does not suit the indenter's shape.
        """
        if not isinstance(item, Indentation):
            raise TypeError(f"indentations must be Indentation instances, got {type(item).__name__}")
        indenter = self.indenter if indenter is None else indenter
        t0 = self.onset_travel(item, indenter)
        start = Pose(item.pose.position + t0 * np.asarray(item.direction), item.pose.quaternion)
        final = Pose(start.position + item.depth * np.asarray(item.direction), item.pose.quaternion)
        check_workspace(indenter.with_pose(final), self.sensor.dimensions)
        frame = self._body_frame(Indentation(start, item.depth, item.direction))
        return frame, item.pose.rotation.as_matrix()

    @staticmethod
    def _push_steps(depth: np.ndarray, pushed: np.ndarray, max_step: float) -> list[dict]:
        """The indenter targets of the load steps from the ``pushed`` depths to ``depth``: even steps of at
        most ``max_step`` (one count for the whole batch)."""
        n = max(1, int(np.ceil(np.max(np.abs(depth - pushed)) / max_step - 1e-9)))
        return [{"indenter": pushed + (depth - pushed) * k / n} for k in range(1, n + 1)]

    def _push(self, depth: np.ndarray, pushed: np.ndarray, max_step: float):
        """Displacement-controlled travel from the current ``pushed`` depths to ``depth`` in solves of at
        most ``max_step``; flags problems whose indenter lost all contact on the way (it passed through
        the shell between surface vertices: the mesh is too coarse for this indenter)."""
        eq = None
        for targets in self._push_steps(depth, pushed, max_step):
            eq = self.solver.solve(targets=targets)
            self._flag_lost_contact(eq, depth > 0)
        return eq

    def _move(self, current: np.ndarray, target: np.ndarray, depth: np.ndarray, max_step: float):
        """Move the pressed indenters from body frames ``current`` to ``target`` (B, 4, 4) with friction, in
        steps that move no point within the outer radius more than ``max_step``; flags lost contact."""
        for poses in self._move_poses(current, target, max_step):
            eq = self.solver.solve(body_poses={"indenter": poses})
            self._flag_lost_contact(eq, depth > 0)
        return eq

    def _move_poses(self, current: np.ndarray, target: np.ndarray, max_step: float) -> list[np.ndarray]:
        """The body frames (B, 4, 4) of the load steps from ``current`` to ``target``: even steps along the
        geodesic that move no point within the outer radius more than ``max_step`` (one count for all)."""
        motion = fem.solver.pose_change(current, target)
        reach = self.sensor.dimensions.outer_radius
        span = np.linalg.norm(motion[:, :3], axis=1) + reach * np.linalg.norm(motion[:, 3:], axis=1)
        steps = max(1, int(np.ceil(span.max() / max_step - 1e-9)))
        return [fem.solver.interpolate_poses(current, target, k / steps) for k in range(1, steps + 1)]

    @staticmethod
    def _lost_contact(eq, pressing: np.ndarray) -> np.ndarray:
        """Problems of ``eq`` whose pressing indenter touches nothing at equilibrium: it passed through the
        shell between surface vertices (the mesh is too coarse for this indenter)."""
        touching = eq.contact_normal_force["indenter"].sum(axis=1) > 0
        return pressing & eq.converged & ~touching

    def _flag_lost_contact(self, eq, pressing: np.ndarray) -> None:
        lost = self._lost_contact(eq, pressing)
        for b in np.nonzero(lost)[0]:
            self.solver.status[b] = fem.SolveStatus.ESCAPED
            eq.status[b] = fem.SolveStatus.ESCAPED
            eq.converged[b] = False

    def indent(self, indentations: list[Indentation], render: bool = True, max_step: float = 0.002):
        """Indent the inflated membrane, up to B indentations in one batched solve; one reading each.

        See :meth:`indent_series` (this is its single level 1.0)."""
        return self.indent_series(indentations, (1.0,), render=render, max_step=max_step)[0]

    def indent_series(
        self,
        indentations: list[Indentation],
        levels,
        render: bool = True,
        max_step: float = 0.002,
        barrier: bool = False,
    ) -> list[list[TactileReading]]:
        """Indent the inflated membrane and read the sensor at several depths along each path.

        Each problem starts from the inflated state with its indenter at contact onset and is pushed
        along its direction; readings are taken at the fractions ``levels`` (increasing, in (0, 1]) of
        its ``depth``, each load step moving the indenter at most ``max_step`` [m] (much less than the
        shell's thickness, so the indenter cannot jump through it). Afterwards the indenters are
        withdrawn and the next call starts from the inflated membrane again. Each problem goes on to its
        next load step as soon as it has reached the current one
        (:meth:`fem.QuasiStaticSolver.solve_sequence`); ``barrier=True`` solves every load step for the
        whole batch before the next (the same readings, the batch waiting at each step for its slowest path).

        Returns:
            readings[level][item]. A problem that fails (no equilibrium, or the indenter lost contact
            while pressing: the mesh is too coarse for the indenter) has ``converged = False`` from that
            level on.

        Raises:
            WorkspaceError: an indenter would reach below the clamped rim plane, or never meets the
                membrane; IndenterError / ValueError: bad input.
        """
        levels = np.asarray(levels, dtype=np.float64).ravel()
        if len(levels) == 0 or np.any(np.diff(levels) <= 0) or levels[0] <= 0 or levels[-1] > 1 + 1e-12:
            raise ValueError(f"levels must increase within (0, 1], got {levels.tolist()}")
        if not max_step > 0:
            raise ValueError(f"max_step must be > 0 m, got {max_step!r}")
        items, frames, rotations = self._prepare(indentations)
        final = np.zeros(self.batch_size)
        final[: len(items)] = [item.depth for item in items]
        pressing = final > 0
        self.solver.set_body_pose("indenter", frames)
        if barrier:
            out, pushed = [], np.zeros(self.batch_size)
            try:
                for level in levels:
                    t_start = time.perf_counter()
                    eq = self._push(level * final, pushed, max_step)
                    pushed = level * final
                    elapsed = time.perf_counter() - t_start
                    out.append(self._readings(eq, pushed, frames, rotations, elapsed, len(items), render))
            finally:
                self._withdraw()
            return out
        # the load steps of every reading level (as _push), solved without a barrier between them: each
        # problem goes on to its next step as soon as it has reached the current one
        steps, reading_steps, pushed = [], [], np.zeros(self.batch_size)
        for level in levels:
            depth = level * final
            steps += self._push_steps(depth, pushed, max_step)
            reading_steps.append(len(steps) - 1)
            pushed = depth
        out, clock = [], [time.perf_counter()]

        def read(step: int, eq) -> None:
            if step in reading_steps:
                depth = levels[reading_steps.index(step)] * final
                now = time.perf_counter()
                out.append(self._readings(eq, depth, frames, rotations, now - clock[0], len(items), render))
                clock[0] = now

        def lost_contact(_steps, part, rows) -> np.ndarray:
            lost = self._lost_contact(part, pressing[rows])
            return np.where(lost, fem.SolveStatus.ESCAPED, fem.SolveStatus.CONVERGED)

        try:
            self.solver.solve_sequence(steps, on_level=read, check=lost_contact)
        finally:
            self._withdraw()
        return out

    def indent_stream(
        self,
        indentations,
        levels,
        on_readings,
        render: bool = True,
        max_step: float = 0.002,
        friction=None,
        progress: bool = False,
        on_invalid=None,
        radius_scale=None,
    ) -> None:
        """Indent any number of paths, B at a time, each problem taking the next path as soon as it has
        finished one (:meth:`fem.QuasiStaticSolver.solve_stream`): a data set's hard paths no longer hold
        up a whole batch while the rest of it idles.

        Each path starts from the inflated membrane (an exact copy of the inflated state) with its
        indenter at contact onset and is pushed along its direction in load steps of at most ``max_step``
        [m], read at the fractions ``levels`` of its depth, as a batch of one path in :meth:`indent_series`
        would (same readings; in a batch of several paths :meth:`indent_series` gives every path the step
        count of the longest push, so its readings differ by the solver tolerance). Afterwards every
        problem is back at the inflated state.

        Args:
            indentations: the paths (:class:`Indentation`), any number.
            levels: increasing fractions in (0, 1] of each path's depth at which it is read: one sequence
                for all paths, or one per path.
            on_readings: ``on_readings(i, readings)`` once path i is done, with one
                :class:`TactileReading` per level (``converged = False`` from the level where it failed:
                no equilibrium, or the indenter lost contact); ``solve_time`` is the wall time from the
                path's start to the reading.
            friction: per-path Coulomb coefficients (default: the simulator's).
            progress: a progress bar over the paths.
            on_invalid: ``on_invalid(i, error)`` for each path that does not suit the sensor or the
                indenter (:meth:`path_frame` raised ``error``); those paths are skipped. None: raise.
            radius_scale: per-path factors on the indenter's radius (sphere, capsule; default 1): paths
                of several indenter sizes share the batch, each problem with its path's radius
                (:meth:`fem.QuasiStaticSolver.set_body_radius`), and read as a simulator built with that
                radius would read them.

        Raises:
            WorkspaceError, IndenterError: a path does not suit the sensor or the indenter (checked for every
                path before any is solved: :meth:`path_frame`), unless ``on_invalid`` takes it.
        """
        items = list(indentations)
        n = len(items)
        per_path = np.ndim(levels[0]) > 0 if len(levels) else False
        if per_path and len(levels) != n:
            raise ValueError(f"give one sequence of levels per path: {n} paths, {len(levels)} sequences")
        fractions = [
            np.asarray(levels[i] if per_path else levels, dtype=np.float64).ravel() for i in range(n)
        ]
        for f in fractions:
            if len(f) == 0 or np.any(np.diff(f) <= 0) or f[0] <= 0 or f[-1] > 1 + 1e-12:
                raise ValueError(f"levels must increase within (0, 1], got {f.tolist()}")
        if not max_step > 0:
            raise ValueError(f"max_step must be > 0 m, got {max_step!r}")

        def plan(i, frame, rotation):  # the load steps of each reading level, as _push (one path's count)
            steps, reads, pushed = [], {}, np.zeros(1)
            for k, level in enumerate(fractions[i]):
                target = np.array([level * items[i].depth])
                steps += self._path_steps(self._push_steps(target, pushed, max_step))
                reads[len(steps) - 1] = (k, target[0], frame, rotation)
                pushed = target
            return steps, reads

        self._run_stream(items, plan, on_readings, render, friction, progress, on_invalid, radius_scale)

    def press_and_move_stream(
        self,
        indentations,
        motions,
        on_readings,
        render: bool = True,
        max_step: float = 0.002,
        friction=None,
        progress: bool = False,
        on_invalid=None,
        radius_scale=None,
    ) -> None:
        """:meth:`press_and_move` for any number of paths, B at a time, each problem taking the next path as
        soon as it has finished one (as :meth:`indent_stream`): each path is pressed to its depth and then
        moved rigidly with friction (shear, twist), read after each motion, as a batch of one path in
        :meth:`press_and_move` reads it (same readings; in a batch of several paths :meth:`press_and_move`
        gives every path the step count of the longest push and move). Afterwards every problem is back at
        the inflated state.

        Args:
            indentations: the presses (:class:`Indentation`), any number.
            motions: one (L_i, 4, 4) sequence of rigid motions per path in the sensor frame, as
                :meth:`press_and_move`'s (level l is the motion from the pressed pose, not cumulative).
            on_readings, render, max_step, friction, progress, on_invalid, radius_scale: as
                :meth:`indent_stream` (one reading per motion level).

        Raises:
            WorkspaceError, IndenterError: as :meth:`indent_stream`; ValueError: bad motions.
        """
        items = list(indentations)
        if len(motions) != len(items):
            raise ValueError(f"give one sequence of motions per path: {len(items)} paths, {len(motions)}")
        moves = []
        for i, m in enumerate(motions):
            m = np.asarray(m, dtype=np.float64)
            if m.ndim != 3 or m.shape[1:] != (4, 4) or len(m) == 0:
                raise ValueError(f"motions of path {i} must have shape (L, 4, 4), got {m.shape}")
            for level in m:
                fem.bodies.check_rigid_transform(level, f"motion of path {i}")
            moves.append(m)
        if not max_step > 0:
            raise ValueError(f"max_step must be > 0 m, got {max_step!r}")

        def plan(i, frame, rotation):
            depth = np.array([items[i].depth])
            steps = self._path_steps(self._push_steps(depth, np.zeros(1), max_step))
            reads, current = {}, frame[None]
            for k, level in enumerate(moves[i]):
                target = (level @ frame)[None]
                steps += [
                    {"body_poses": {"indenter": pose[0]}}
                    for pose in self._move_poses(current, target, max_step)
                ]
                reads[len(steps) - 1] = (k, depth[0], target[0], level[:3, :3] @ rotation)
                current = target
            return steps, reads

        self._run_stream(items, plan, on_readings, render, friction, progress, on_invalid, radius_scale)

    @staticmethod
    def _path_steps(steps: list[dict]) -> list[dict]:
        """One path's load steps (of a batch of one, :meth:`_push_steps`) as scalar stream levels."""
        return [{"indenter": float(t["indenter"][0])} for t in steps]

    def _run_stream(
        self, items, plan, on_readings, render, friction, progress, on_invalid, radius_scale=None
    ) -> None:
        """Paths through :meth:`fem.QuasiStaticSolver.solve_stream` (:meth:`indent_stream`,
        :meth:`press_and_move_stream`): ``plan(i, frame, rotation)`` gives path i's load steps (stream
        levels) and its readings {step: (reading index, travel [m], body frame (4, 4), indenter rotation
        (3, 3))} from its body frame at contact onset and the indenter's rotation."""
        n = len(items)
        base = float(next(b.friction for b in self.solver.bodies if b.name == "indenter"))
        mu = np.full(n, base) if friction is None else np.asarray(friction, dtype=np.float64).ravel()
        if mu.shape != (n,) or not np.all(np.isfinite(mu)) or np.any(mu < 0):
            raise ValueError(f"friction must hold {n} finite coefficients >= 0, got {friction!r}")
        scale = np.ones(n) if radius_scale is None else np.asarray(radius_scale, dtype=np.float64).ravel()
        if scale.shape != (n,) or not np.all(np.isfinite(scale)) or np.any(scale <= 0):
            raise ValueError(f"radius_scale must hold {n} finite factors > 0, got {radius_scale!r}")
        if np.any(scale != 1) and not isinstance(self.indenter, (SphereIndenter, CapsuleIndenter)):
            raise IndenterError(
                f"only sphere and capsule radii can be scaled, got {type(self.indenter).__name__}"
            )
        base_radius = getattr(self.indenter, "radius", 0.0)
        frames, rotations = np.zeros((n, 4, 4)), np.zeros((n, 3, 3))
        valid = []  # the paths to solve (job j is path valid[j])
        for i, item in enumerate(items):
            indenter = (
                self.indenter if scale[i] == 1 else replace(self.indenter, radius=base_radius * scale[i])
            )
            try:
                frames[i], rotations[i] = self.path_frame(item, indenter)
            except IndenterError as error:
                if on_invalid is None:
                    raise
                on_invalid(i, error)
            else:
                valid.append(i)
        depth = np.array([item.depth for item in items])
        path_of = np.array(valid, dtype=np.int64)  # job j of the stream is path path_of[j]
        jobs, reads = [], []
        for i in valid:
            steps, at = plan(i, frames[i], rotations[i])
            jobs.append(steps)
            reads.append(at)
        template = self._template()
        solver = self.solver
        coefficients = np.full(self.batch_size, base)  # each problem's friction, that of its path
        begun = np.zeros(n)
        readings: dict[int, dict[int, TactileReading]] = {}

        def start(problems, jobs_started):
            ids = path_of[jobs_started]
            solver.copy_state_from(template, rows=np.zeros(len(problems), dtype=np.int64), into=problems)
            if np.any(scale[ids] != 1):
                solver.set_body_radius("indenter", base_radius * scale[ids], rows=problems)
            solver.set_body_pose("indenter", frames[ids], rows=problems)
            coefficients[problems] = base  # the template's
            if np.any(mu[ids] != base):
                coefficients[problems] = mu[ids]
                solver.set_friction("indenter", coefficients)
            begun[ids] = time.perf_counter()

        def on_levels(jobs_reached, steps, part):
            now = time.perf_counter()
            for r, (j, step) in enumerate(zip(jobs_reached.tolist(), steps.tolist())):
                at, i = reads[j].get(step), int(path_of[j])
                if at is None:
                    continue
                k, travel, frame, rotation = at
                (reading,) = self._readings(
                    part.take(np.array([r])), np.array([travel]), frame[None], rotation[None],
                    now - begun[i], 1, render,
                )  # fmt: skip
                got = readings.setdefault(i, {})
                got[k] = reading
                if len(got) == len(reads[j]):
                    on_readings(i, [got[m] for m in range(len(reads[j]))])
                    del readings[i]

        def lost_contact(jobs_reached, _steps, part):
            lost = self._lost_contact(part, depth[path_of[jobs_reached]] > 0)
            return np.where(lost, fem.SolveStatus.ESCAPED, fem.SolveStatus.CONVERGED)

        try:
            solver.solve_stream(jobs, start, on_levels, check=lost_contact, progress=progress)
        finally:  # every problem back at the inflated state, with the simulator's friction
            B = self.batch_size
            solver.copy_state_from(template, rows=np.zeros(B, dtype=np.int64))
            solver.set_friction("indenter", base)
        if readings:  # cannot happen: solve_stream reports every level of every job
            raise RuntimeError(f"the stream left paths {sorted(readings)} incomplete")

    def press_and_move(
        self,
        indentations: list[Indentation],
        motions,
        render: bool = True,
        max_step: float = 0.002,
    ) -> list[list[TactileReading]]:
        """Press each indenter to its depth, then move it rigidly with friction (shear, twist) and read.

        Args:
            indentations: up to B presses (pose, depth, direction), as :meth:`indent`.
            motions: (L, n, 4, 4) or (L, 4, 4) rigid motions in the sensor frame, each applied to the
                pressed indenter (not cumulative: level l is the motion from the pressed pose), read at each
                level in order; the indenter travels between levels along the geodesic, dragging the
                membrane where friction holds it (``solve(body_poses=...)`` of the FEM engine), in load
                steps of at most ``max_step`` [m] of motion of any point within the outer radius.

        Returns:
            readings[level][item], as :meth:`indent_series`.
        """
        items, frames, rotations = self._prepare(indentations)
        n = len(items)
        M = np.asarray(motions, dtype=np.float64)
        if M.ndim == 3:
            M = np.broadcast_to(M[:, None], (M.shape[0], n, 4, 4))
        if M.ndim != 4 or M.shape[1:] != (n, 4, 4) or len(M) == 0:
            raise ValueError(f"motions must have shape (L, {n}, 4, 4) or (L, 4, 4), got {np.shape(motions)}")
        for m in M.reshape(-1, 4, 4):
            fem.bodies.check_rigid_transform(m, "motion")
        if not max_step > 0:
            raise ValueError(f"max_step must be > 0 m, got {max_step!r}")
        depth = np.zeros(self.batch_size)
        depth[:n] = [item.depth for item in items]
        s = self.solver
        s.set_body_pose("indenter", frames)
        out = []
        try:
            t_start = time.perf_counter()
            self._push(depth, np.zeros(self.batch_size), max_step)
            current = frames.copy()
            for level in M:
                target = current.copy()
                target[:n] = level @ frames[:n]
                eq = self._move(current, target, depth, max_step)
                current = target
                turned = rotations.copy()
                turned[:n] = level[:, :3, :3] @ rotations[:n]
                out.append(
                    self._readings(eq, depth, current, turned, time.perf_counter() - t_start, n, render)
                )
                t_start = time.perf_counter()
        finally:
            self._withdraw()
        return out

    def _withdraw(self) -> None:
        """Take the indenters away (the elastic state is path independent once contact is lost); re-inflate
        if any problem failed, so the next call starts from the inflated membrane."""
        s = self.solver
        if (s.status == fem.SolveStatus.CONVERGED).all():
            back = s.solve(targets={"indenter": 0.0})
            s.set_body_pose("indenter", self._idle_poses())
            if back.converged.all():
                return
        self._inflate()

    # ------------------------------------------------------------------ outputs
    def _readings(self, eq, depth, frames, rotations, elapsed, count, render=True) -> list[TactileReading]:
        clamped = self.sensor.clamped_vertices
        x = eq.positions
        out = []
        for b in range(count):
            support = eq.reaction_force[b, clamped]  # s_i, on the membrane
            gas = eq.pressure_force[b]  # f_i
            on_housing = -(support.sum(axis=0) + gas.sum(axis=0))
            torque = -(np.cross(x[b, clamped], support).sum(axis=0) + np.cross(x[b], gas).sum(axis=0))
            frame = None
            if render and self.camera is not None and eq.converged[b]:
                frame = self.camera.render(*self.sensor.inner_surface(x[b]), noisy=False)
            out.append(
                TactileReading(
                    positions=x[b].copy(),
                    depth=frame,
                    contact_force=eq.body_force["indenter"][b].copy(),
                    base_wrench=np.concatenate([on_housing, torque]),
                    rim_force=-support.sum(axis=0),
                    gauge_pressure=float(eq.gauge_pressure[b]),
                    gas_volume=float(eq.cavity_volume[b] + self.sensor.dimensions.housing_volume),
                    depth_travel=float(depth[b]),
                    indenter_position=frames[b, :3, 3] + depth[b] * frames[b, :3, 2],
                    indenter_pose=Pose.from_rotation(
                        frames[b, :3, 3] + depth[b] * frames[b, :3, 2], Rotation.from_matrix(rotations[b])
                    ),
                    converged=bool(eq.converged[b]),
                    solve_time=elapsed,
                )
            )
        return out

    def reference_depth(self) -> DepthFrame:
        """The camera's noise-free frame of the inflated membrane (the pre-contact reference image)."""
        if self.camera is None:
            raise ValueError("this simulator has no camera (intrinsics=None)")
        return self.camera.render(*self.sensor.inner_surface(self.reference.positions), noisy=False)

    def pole_indentation(self, depth: float, pose_offset=(0.0, 0.0)) -> Indentation:
        """A vertical indentation (direction -z) above the point ``pose_offset`` (x, y) [m] of the pole."""
        top = self.sensor.dimensions.outer_pole[2] + 0.05
        return Indentation(Pose((pose_offset[0], pose_offset[1], top)), depth, (0.0, 0.0, -1.0))
