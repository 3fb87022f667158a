"""The squeeze ramp (thesis §7.4): parallel-jaw fingers close on the object with a prescribed total force.

Each grasp of a :class:`~defgraspnets.grasp.sampler.GraspSet` becomes one problem of a batched
:class:`~defgraspnets.fem.QuasiStaticSolver`: the two finger pads are rigid rounded boxes placed at
first contact (the analytic finger joint states), both driven by one shared, force-controlled travel
(the fingers of a parallel-jaw gripper move together, like the Franka hand's mimic joint). The
prescribed force is the *total normal grasp force* F_g, the sum of the two fingers' normal forces
(each finger presses with F_g / 2 at equilibrium), ramped from 0 to ``max_force`` in ``steps`` equal
steps in zero gravity.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from defgraspnets import fem

from .gripper import FRANKA_HAND, ParallelJawGripper
from .sampler import GraspSet

__all__ = [
    "FINGER_NAMES",
    "FIRST_STEP_BUDGET_FACTOR",
    "GRIP_DOF",
    "finger_contact_poses",
    "make_squeeze_solver",
    "pad_shape",
    "squeeze_ramp",
    "squeeze_solver_options",
    "squeeze_stream",
]

FINGER_NAMES = ("left_finger", "right_finger")
GRIP_DOF = "grip"
#: a squeeze ramp's first force step may spend this many times the Newton budget of a later one
#: (``SolverOptions.max_newton_first_step``, when not given; :func:`squeeze_solver_options` says why)
FIRST_STEP_BUDGET_FACTOR = 2


def pad_shape(gripper: ParallelJawGripper = FRANKA_HAND) -> fem.RoundedBox:
    """The finger pad as an exact rigid shape in its finger frame: a box with rounded edges whose flat
    contact face lies on y = 0 (outward normal +y, the closing direction) and whose body fills
    -thickness <= y <= 0. Its signed distance is smooth across the rounded edges, which a tessellated pad
    is not (Newton stalls on the kinks of a faceted rim)."""
    width, thickness, length = gripper.pad_size
    return fem.RoundedBox(
        half_extents=(width / 2, thickness / 2, length / 2),
        radius=gripper.pad_edge_radius,
        center=(0.0, -thickness / 2, 0.0),
    )


def finger_contact_poses(grasps: GraspSet, gripper: ParallelJawGripper = FRANKA_HAND) -> np.ndarray:
    """(G, 2, 4, 4) finger frames (object frame) with each pad at first contact.

    ``grasps``: a :class:`GraspSet`, or anything with ``poses`` (G, 4, 4) of the open gripper and
    ``closing_distances`` (G, 2) [m] (e.g. grasps refined by the planner)."""
    openings = gripper.opening_from_closing(grasps.closing_distances)
    return np.stack([gripper.finger_poses(p, q) for p, q in zip(grasps.poses, openings)])


def squeeze_solver_options(**overrides) -> fem.SolverOptions:
    """Solver settings of the squeeze ramp (``overrides``: SolverOptions fields; None keeps the squeeze
    default, as the entry points' ``null`` config values do): the engine's defaults with the C2 contact onset
    (``contact_smoothing`` = 1e-2 h, as the tactile sensor's). Vertices of a coarse object mesh graze the rim
    of a pad's contact patch; with the plain quadratic penalty Newton then toggles them in and out of contact
    (measured on 8 Franka grasps of a 960-vertex box, 0-15 N in 50 steps on 2 CPU cores: 317 s and up to 850
    Newton iterations per grasp; with a 1e-3 h onset 87 s and at most 500). The onset adds at most
    ``contact_smoothing / 2`` h of penetration.

    1e-2 h instead of 1e-3 h (the default until session 15), on the FEM benchmark (one H100, 100 antipodal
    grasps of that box, 0-15 N in 50 steps, dense): at 200 kPa 116.9 -> 73.7 s, 2380 -> 1444 lockstep Newton
    iterations, 97 of 100 converged either way (95 the same), largest penetration 7 -> 22 um; at 20 kPa
    187.2 -> 170.6 s, 1585 -> 1216 iterations, 47 of 100 either way (42 the same), 56 -> 71 um
    (``benchmarks/fem_cuda_100x50_dense_neohookean*_smooth1e-*.json``). Final displacements moved by at most
    0.28 % (200 kPa, grasps 0-7) and 0.37 % (20 kPa, grasps 16-23) of the largest (2-core CPU, "direct").
    It does not free the stalled soft grasps (below): grasps 16 and 17 at 20 kPa fail at step 17 instead of
    18.

    The Newton tolerance is ``rtol`` = 1e-5 (force imbalance per component below 1e-5 of the largest force;
    commercial implicit FEM codes default to about 5e-3): the same 8 grasps then take 53 s and at most 256
    Newton iterations; the fields of a grasp dataset do not change at that level.

    Friction capacities are consistent with the normal forces to 1e-3 of the total (``friction_rtol``,
    instead of per contact to ``rtol``): 30 % fewer Newton iterations on a tilted grasp.
    A grasp may spend at most 200 Newton iterations per force step (``max_newton_per_solve``; 400 in the
    first, below; an easy grasp needs 3-10): the batch advances in lockstep, and out of 100 grasps of the
    benchmark box a few tilted ones spent 1000-2000 iterations per step at 10-15 N (friction re-lagging),
    holding up the other 97. Those grasps are flagged NOT_CONVERGED and left out of data sets, as the thesis
    leaves out unstable grasps.

    Friction has a stick zone of at least ``friction_stick_slip`` = 5e-3 h (a sticking contact
    shifts by up to 5e-3 h before it slides, 14 um on a 1000-vertex 30 mm fTetWild cube; commercial penalty
    friction defaults to an elastic slip of the same order, e.g. Abaqus' slip tolerance of 0.005 of the
    contact face size). With the exact stick zone mu N / k_i (k_i the normal penalty stiffness, 1000 E A /
    h: micrometres and less) the first force step of a soft object fails wherever the pads first touch a
    few vertices, as on the facets of an fTetWild "flat" face tilted by up to 6 degrees against the pad:
    within one step the pads travel ~1 mm at E = 10 kPa while the contacts grow from 1-2 to 12-16
    vertices, and a slipping contact's Hessian has no stiffness along its slip, so Newton's step runs
    through the slip reversal; the line search cuts it to 1/16 and the next step reverses it (successive
    steps at cosine -1.00, the residual stuck at 8 times the load) until the step's 200-iteration budget is
    spent. Measured on the 30 mm fTetWild cube (2-core CPU, "direct", grasps 0, 4, ..., 36 of the data
    path's 100, 0-15 N in 50 steps; ``benchmarks/squeeze_stick_zone_cpu.md``):

        stick zone           E = 10 kPa failed, Newton    100 kPa failed, Newton    10 MPa failed, Newton
        exact (0)            8 of 10, 4863                3 of 10, 7241             0 of 10, 2085
        5e-3 h (default)     6 of 10, 8538                0 of 10, 8554             0 of 10, 1952

    The first force step (0.3 N at 10 kPa) of the 6 grasps of that set that fail it with the exact stick
    zone converges in 572 instead of 1319 (failing) Newton iterations (1e-3 h: 2 of 6 still fail; 2e-3 h: 2;
    1e-2 h: none). The 6 failures left at 10 kPa are no solver stall but the force maximum of the object's
    own equilibrium path: squeezed to a pad gap of 9-12 mm of its 30 mm at 5-10 N, the cube gives way (under
    travel control the same grasp's force peaks at 5.12 N at 9.25 mm of travel per pad and drops to 2.5 N at
    10 mm, where the object has turned by ~1.5 degrees and slid ~1 mm across the grasp axis); a force ramp
    cannot pass that, and the ramp is stored as failed with its fields up to the last force reached, as the
    thesis leaves out grasps with unstable dynamics. Where both converge the final fields move by little
    against the friction path's own spread: at 10 MPa (displacements 30-350 um, where the stick zone is
    largest against them) mean von Mises stress by 0.1-1.4 % (median 0.6 %) and the deformation with the
    rigid motion removed by 1-6 % of its largest value (median 2.8 %); at 10 kPa, first step (268-vertex
    mesh), the deformation by 1.4-5.3 % against 0.07-6.4 % between two exact-friction paths (plain and
    stabilized increments). ``friction_stick_slip=0.0`` gives the exact stick zone of the data sets made
    before.

    Earlier, on the structured box: at E = 20 kPa its failing grasps stall where the pad's end
    rim meets the compressed top edge: Newton proposes millimetre moves of a vertex there and the line
    search cuts them to 1/64-1/32 because the *penalty* energy rises (a vertex a few micrometres outside
    the rim, or sliding over it, penetrates), while the friction energy keeps falling along the step. A
    stick zone of 0.05 h (0.29 mm on that coarser mesh, a fifth of the grasps' displacements; CPU,
    "direct", 0-15 N in 50 steps) changed 0 -> 1 converged of 8 such grasps and moved the final fields by
    5-12 % of the largest displacement at 200 kPa: a stick zone of that size is no harmless knob.

    A failed load increment is retried with the friction normal forces re-lagged at every Newton iteration
    (``relag_friction_on_retry``) from its second failed attempt on (the first retry keeps the frozen lags).
    Where the pads first touch a few vertices of a stiff curved fTetWild mesh, those vertices' normal forces
    change much within an increment and the frozen lags' re-lag cycles never settle: a 294-vertex cone, 12
    antipodal grasps, 0-15 N in 10 steps (2-core CPU, dense) converged 0 of 12 at E = 10 MPa and 4 of 12 at
    300 kPa with frozen lags, 10 of 12 at both with the re-lag from the first failed attempt (1e-3 h onset;
    von Mises stress within 0.16 % where both converge); with the 1e-2 h onset 10 and 11 of 12 with the
    re-lag from the first attempt, 9 and 11 of 12 from the second. On the soft box the re-lag from the
    first attempt cost grasps that plain halving saves; on the FEM benchmark (one H100, 100 grasps of the
    960-vertex box, 0-15 N in 50 steps, 1e-2 h onset; ``benchmarks/fem_cuda_100x50_*relag*.json``):

        re-lag on retry      20 kPa converged, s     200 kPa converged, s
        never                57, 193.0               -
        from the 1st         47, 170.6               97, 73.7
        from the 2nd         54, 173.4               100, 82.6

    Newton steps are capped at ``max_step_fraction`` = 0.01 of the object's bounding-box diagonal (the
    engine's default is 0.1). Pads that first touch a curved surface (a capsule, a cylinder's side) meet
    one vertex each, offset across it by up to the mesh spacing, and their forces form a couple that only
    friction can hold; at the first Newton iterations of the first step no normal force, so no friction,
    exists yet, the object's roll about its axis is free, and a step capped at 0.1 of the diagonal rolls
    it by several facets before the friction re-lags catch it: the object spins out (ESCAPED) or Newton
    stalls (NOT_CONVERGED), or it converges at an equilibrium reached by a frictionless roll. Measured on
    16 antipodal grasps (seed 0) per object and modulus, ~300-vertex fTetWild meshes, 0-15 N in 10 steps,
    2-core CPU, "direct" (converged of 16, lockstep Newton iterations, seconds; 0.1 -> 0.01):

        capsule_r20_l40    3 MPa     5 -> 16, 380 -> 320, 48 -> 30 s
        capsule_r20_l40    300 kPa   5 -> 16, 558 -> 624, 40 -> 45 s
        cylinder_r25_h100  3 MPa     8 -> 16, 332 -> 284, 35 -> 22 s
        cone_rb30_rt15_h50 3 MPa     7 -> 10, 480 -> 310, 48 -> 31 s
        cuboid_50x50x50    300 kPa  12 -> 16, 568 -> 458, 41 -> 28 s
        ellipsoid_30x30x30 300 kPa  16 -> 16, 284 -> 240, 20 -> 17 s

    Of 11 grasps that converge with both caps (cuboid_50x50x50 at 300 kPa, capsule_r20_l40 at 3 MPa), 6
    end in the same state (to 7e-5 of the largest displacement); in the other 5 the 0.1 cap had moved the
    object before friction held it, into another equilibrium of the frictional path: 3 capsule grasps
    placed differently by 1.2-1.4 times their displacement with von Mises stress within 1.2 %, a cuboid
    grasp (stress 51 instead of 55 kPa) and a capsule grasp rolled by 35 mm at 1.5 N with mu = 0.7
    (stress 48 instead of 43 kPa). Data generation of 18 objects (17 primitives + lemon), 16 grasps x 4
    moduli x 10 steps, on one H100 (``benchmarks/datagen_step_cap_ab_h100.json``): 906 -> 1045-1048 of 1152
    ramps converged (capsule_r20_l40 21 -> 62 of 64, cylinder_r25_h100 32 -> 63, lemon 34 -> 64; no
    ESCAPED or PINCHED ramp is left), 250 -> 283 s with warm kernel caches: the same time per converged
    ramp (0.27 s).

    Stiff curved first contacts can also crawl: the Newton step is dominated by the object's free rigid
    modes, so the cap shrinks its useful part, and a grasp spends its 200 iterations in the first step
    (cylinder_r20_h40 at 10 MPa: 8 of 16 fail so). Released increment stabilization
    (``stabilization=1e-4, stabilization_release=True``: springs guide each increment, then Newton
    finishes without them) converged 89 instead of 70 of 96 ramps on six hard (object, modulus) pairs
    (2-core CPU, same time) and 1130 instead of 1048 of the 1152 ramps above (H100, 387 s against 399 s,
    both with kernel compilation). Since session 24 it is the default (``stabilization=0.0`` turns it off):
    over those 18 objects (H100, ``scripts/compare_grasp_data.py``, ``benchmarks/datagen_step_cap_ab_h100``)
    1129 instead of 1045 of 1152 ramps converge, and of the 1036 that converge both ways 997 end in the
    same state (mean von Mises stress within 0.1 % in 962, median difference 9e-5). The other 39 differ by
    a rigid turn of 1-22 degrees, about an axis within 20 degrees of the closing direction in 34: the spin
    about the grasp axis, which zero gravity and two pads leave nearly free, so friction holds it wherever
    the path left it; 19 of them differ by more than 1 % in mean stress (at most 14 %). The stabilized path
    keeps that spin small and the same on both devices: on cone_rb25_rt10_h60 at 10 MPa, grasps 12-14 end
    turned by 0.06 degrees stabilized on the CPU and on the GPU, by 12.5-13 (GPU) or 0.35-0.55 (CPU)
    degrees with the plain solve, and by 0.14-2.8 degrees plain with 40 instead of 10 steps, at the same
    mean stress (4.468 kPa) every way (session 20's "other equilibria" on the 2-core CPU were not re-run).

    A ramp that passed a force maximum of the object's equilibrium path (the soft cube above, crushed until
    it gives way) is flagged FORCE_MAXIMUM (status 6) once two failed increments of a force step ran the
    grip's travel past 3 times what the last converged increment's secant stiffness predicts for their
    force change (``force_maximum_runaway`` = 3, ``force_maximum_attempts`` = 2; since session 38), instead
    of halving the increment until the step's 200 Newton iterations are spent (NOT_CONVERGED). On the
    268-vertex fTetWild cube (2-core CPU, "direct", grasps 0, 4, ..., 96 of 100, 0-15 N in 50 steps) the
    failing step cost 36 % of such a ramp's Newton iterations and time (the 921-vertex data-path cube:
    24 %); 10 ramps at 10 kPa are flagged at the same step as before with 22 % fewer Newton iterations
    (5920 -> 4619; 921 vertices: 15 %), and no converging ramp (153, at 10 kPa, 100 kPa and 10 MPa, and
    tilted or curved first contacts of a cone, a capsule and a cylinder) ever met the test: their failed
    increments stayed within 0.99 times the secant's prediction, the force maximum's ran 5-21 times past
    it (``SolverOptions.force_maximum_runaway``, ``benchmarks/squeeze_force_maximum_cpu.md``). Stalls that
    are no force maximum stay NOT_CONVERGED. The data sets leave the ramp out either way; its fields up
    to the last force reached do not change. ``force_maximum_runaway=0.0`` turns it off.

    On soft objects these runaways mark where the object starts to fold onto itself, which the FEM (no
    self-contact) lets it do (session 40, ``benchmarks/squeeze_soft_failures_cpu.md``): cuboid_70x35x20 at
    10 kPa, grasp 0, flagged at 6.0 N (its force was still rising at 1.6 N/mm under travel control), and
    cylinder_r20_h40 at 21.5 kPa, grasp 0, flagged at 11.7 N, both reach 15 N when their increments get 200
    Newton iterations (``force_maximum_snap``: the path jumps at the same force, the object turns and
    slides between the pads by millimetres), but the states after the jump pass through themselves (25-35
    surface vertices inside the object's own tets, none before it). So the flag stays the squeeze path's
    answer (``force_maximum_snap`` = 0 here): those ramps are no data either way, and the data path would fail
    the jumped ones as self-intersecting (``STATUS_SELF_INTERSECTING``) after 2-4 times the Newton iterations.

    A stiff curved object whose first contact is a point must still roll into the grasp: its stabilized first
    increment converges, but the released solve stalls on the near-free rigid mode the springs held
    (``benchmarks/squeeze_torus_first_step_cpu.md``). Since session 39 the released solve's failure is
    followed by up to 40 re-referenced stabilized solves whose springs weaken x0.25 from one to the next
    (``stabilization_relax=40``, ``stabilization_relax_decay=0.25``: a proximal-point loop that converges
    superlinearly), then a new release; ramps whose releases all converge are unchanged bit for bit. Measured
    on the 2-core CPU ("direct", the step's 200-iteration budget, ``benchmarks/squeeze_relax_cpu.md``): the
    first force step of the 997-vertex fTetWild torus at 10 MPa, grasps 20-59, 24 -> 33 of 40 converge with
    5034 -> 3836 Newton iterations (constant springs, session 38: 29); annulus_ro45_ri35_h20 (1023 vertices,
    4.64 MPa), grasps 0-24, 0-1.5 N in 5 steps: 13 -> 17 of 25; the 268-vertex cube, grasps 0, 4, ..., 96,
    0-15 N in 50 steps: 10 kPa and 100 kPa bit for bit, 10 MPa 24 of 25 either way (grasp 4 gained, grasp 96,
    which bisection saves, lost; 5174 -> 4935 Newton iterations). Four grasps that bisection saves end on
    another path of the frictional problem (e.g. the annulus' grasp 5: pad travel 1.487 instead of 1.451 mm at
    1.5 N). ``stabilization_relax=0`` turns it off (the data sets before session 39).

    That loop, the roll into the grasp, is the first force step's work: the later steps mostly start from a
    settled grip. Since session 40 the first force step of a ramp may spend ``FIRST_STEP_BUDGET_FACTOR`` = 2
    times the later steps' budget (``max_newton_first_step`` = 400 with the 200 above; given explicitly it is
    kept, and ``max_newton_per_solve=0`` leaves both unlimited). Measured on the 2-core CPU ("direct",
    ``benchmarks/squeeze_first_step_budget_cpu.md``): annulus_ro45_ri35_h20 at 4.64 MPa, grasps 0-24 of the
    data path's 100, 0-1.5 N in 5 steps, 18 -> 25 of 25 ramps (the 7 gained converge their first step in
    281-385 Newton iterations, the next in 51-103, and end at 0.40-0.87 mm of pad travel), 4977 -> 6273 Newton
    iterations; cone_rb20_rt5_h80 at 10 MPa (the same grasps and ramp) 20 -> 24 of 25 (3789 -> 4770; grasp 14
    needs 692); the 268-vertex cube, grasps 0, 4, ..., 96, 0-15 N in 50 steps, at 10 MPa 24 -> 25 (grasp 96,
    which the relax loop had lost, in 271), at 10 kPa 14 of 25 either way (grasp 24 fails its first step after
    414 instead of 224 iterations). Every ramp whose first step converges within 200 is unchanged bit for bit
    (38 of the annulus and cone, 48 of the cube), and so is the cube at 100 kPa, where 400 for every step
    would save one more ramp (grasp 48, whose second step needs 221: the later steps' budget stops tilted
    grasps whose friction keeps re-lagging, so it stays). ``max_newton_first_step=200`` gives the data sets
    before session 40.

    Frozen friction lags are checked early (``friction_lag_check`` = 1000, since session 44): a problem whose
    residual is within 1000 times the tolerance has its lags' consistency checked and is re-lagged at once
    where a contact's capacity error exceeds 10 times the residual, instead of first converging the lagged
    problem and then starting over. Measured with the squeeze defaults above (so with the 5e-3 h stick zone;
    with the exact stick zone it failed 1 of 4 stiff-cylinder first steps in session 35, the engine's default
    stays 1): the FEM benchmark (one H200, 100 grasps of the 960-vertex box, 0-15 N in 50 steps,
    ``dense_banded``) 38.6 -> 35.3 s in one lease, 40.9 -> 37.2 s in another, slowest grasp 1573 -> 1484 and
    -> 1428 Newton iterations, 100 of 100 converged every time (``benchmarks/fem_cuda_*_h200_s44.json``); on
    the 2-core CPU ("direct", 16 antipodal grasps of each test mesh, seed 0, 0-15 N in 10 steps; converged of
    16, summed Newton iterations, with 1 -> 1000; ``benchmarks/squeeze_friction_lag_check_cpu_s44.json``):
    cylinder_r20_h40 and cone_rb25_rt10_h60 at 10 MPa 16 -> 16, annulus_ro45_ri35_h20 at 4.64 MPa 13 -> 16
    (5941 -> 5099), capsule_r20_l40 at 100 kPa 16 -> 16 (3479 -> 2913), cylinder_r20_h40 at 10 kPa 12 -> 12
    (4414 -> 3752; the same four force maxima), cuboid_30x30x30 at 21.5 kPa 12 -> 12 (6178 -> 5370; the same
    four fail, two stalls and two force maxima before, four force maxima after); the data path's ~1000-vertex
    meshes, 8 grasps each: torus_R30_r10 at 100 kPa 6 -> 8 (2996 -> 2726), ellipsoid_40x25x15 at 100 kPa,
    cone_rb30_rt15_h50 at 10 MPa, bunny at 1 MPa and cylinder_r25_h100 at 46.4 kPa 8 -> 8 with 6-17 % fewer
    Newton iterations. ``friction_lag_check=1`` gives the data sets before session 44.
    """
    overrides = {key: value for key, value in overrides.items() if value is not None}
    budget = overrides.get("max_newton_per_solve", 200)
    if isinstance(budget, bool) or not isinstance(budget, (int, np.integer)):
        budget_first = None  # (SolverOptions judges the budget)
    else:
        budget_first = FIRST_STEP_BUDGET_FACTOR * budget
    return fem.SolverOptions(
        **{
            "max_step_fraction": 0.01,
            "contact_smoothing": 1e-2,
            "friction_stick_slip": 5e-3,
            "rtol": 1e-5,
            "friction_rtol": 1e-3,
            "max_newton_per_solve": budget,
            "max_newton_first_step": budget_first,
            "relag_friction_on_retry": 2,
            "stabilization": 1e-4,
            "stabilization_release": True,
            "force_maximum_runaway": 3.0,
            "force_maximum_attempts": 2,
            "force_maximum_snap": 0,
            "stabilization_relax": 40,
            "stabilization_relax_decay": 0.25,
            "friction_lag_check": 1000.0,
            **overrides,
        }
    )


def make_squeeze_solver(
    mesh: fem.TetMesh,
    grasps: GraspSet,
    material: fem.Material | Sequence[fem.Material],
    friction: float = 0.7,
    gripper: ParallelJawGripper = FRANKA_HAND,
    device=None,
    options: fem.SolverOptions | None = None,
) -> fem.QuasiStaticSolver:
    """A solver with one problem per grasp: pads at first contact, closing along their normals.
    ``options`` default to :func:`squeeze_solver_options`."""
    if options is None:
        options = squeeze_solver_options()
    if len(grasps.poses) == 0:
        raise ValueError("no grasps to simulate")
    pad = pad_shape(gripper)
    # in the finger frame the contact face normal, i.e. the closing direction, is +y
    bodies = [
        fem.RigidBody(name, pad, control=fem.Control.force((0.0, 1.0, 0.0), dof=GRIP_DOF), friction=friction)
        for name in FINGER_NAMES
    ]
    solver = fem.QuasiStaticSolver(
        mesh, bodies, material, batch_size=len(grasps.poses), device=device, options=options
    )
    poses = finger_contact_poses(grasps, gripper)
    for i, name in enumerate(FINGER_NAMES):
        solver.set_body_pose(name, poses[:, i])
    return solver


def squeeze_stream(
    solver: fem.QuasiStaticSolver,
    finger_poses: np.ndarray,
    materials: Sequence[fem.Material],
    on_steps: Callable[[np.ndarray, np.ndarray, fem.Equilibrium], None],
    max_force: float = 15.0,
    steps: int = 50,
    progress: bool = False,
) -> None:
    """Squeeze ramps of J (grasp, material) pairs streamed through the B problems of a squeeze solver
    (:meth:`fem.QuasiStaticSolver.solve_stream`): a problem that has finished its ramp (or failed) takes
    the next one at the next Newton pass, so the slow ramps' tails overlap with the others' work.

    Each ramp starts at rest with the pads at first contact (``finger_poses[j]``, (J, 2, 4, 4) finger
    frames in the object frame, :func:`finger_contact_poses`) and the material ``materials[j]``, and
    reaches the equilibria :func:`squeeze_ramp` gives it in a batch of its own (bit for bit with the
    solvers that factor one problem at a time: "direct", "dense").

    Args:
        solver: a squeeze solver (:func:`make_squeeze_solver`; any grasps, any batch size B): its
            problems are the slots. It is left with the last ramps' states.
        on_steps: ``on_steps(ramp_ids, step_indices, part)``: (ramp, step) pairs just reached and their
            equilibria (row i of ``part``); every step of every ramp once, a ramp's steps in order (a
            failed ramp reports its later steps flagged, as :func:`squeeze_ramp` does).
        max_force, steps: the ramp, 0 -> ``max_force`` [N] total normal grasp force in ``steps`` steps.
        progress: a progress bar over the ramps.
    """
    if not np.isfinite(max_force) or max_force <= 0:
        raise ValueError(f"max_force must be a positive force in newtons, got {max_force!r}")
    finger_poses = np.asarray(finger_poses, dtype=float)
    if finger_poses.ndim != 4 or finger_poses.shape[1:] != (2, 4, 4):
        raise ValueError(f"finger_poses must be (J, 2, 4, 4), got {finger_poses.shape}")
    materials = list(materials)
    if len(materials) != len(finger_poses):
        raise ValueError(f"{len(finger_poses)} ramps need as many materials, got {len(materials)}")
    # the rest state every ramp starts from: a one-problem solver of the same bodies and options
    template = fem.QuasiStaticSolver(
        solver.mesh, solver.bodies, materials[0] if materials else solver.materials[0], batch_size=1,
        device=solver.device, options=solver.options,
    )  # fmt: skip
    forces = [max_force * s / steps for s in range(1, steps + 1)]
    ramp = [{GRIP_DOF: force} for force in forces]

    def start(problems: np.ndarray, ramp_ids: np.ndarray) -> None:
        solver.copy_state_from(template, rows=np.zeros(len(problems), dtype=int), into=problems)
        solver.set_material([materials[j] for j in ramp_ids], rows=problems)
        for i, name in enumerate(FINGER_NAMES):
            solver.set_body_pose(name, finger_poses[ramp_ids, i], rows=problems)

    solver.solve_stream([ramp] * len(finger_poses), start, on_steps, progress=progress)


def squeeze_ramp(
    solver: fem.QuasiStaticSolver,
    max_force: float = 15.0,
    steps: int = 50,
    progress: bool = False,
    on_step: Callable[[int, float, fem.Equilibrium], None] | None = None,
    barrier: bool = False,
) -> list[fem.Equilibrium]:
    """Ramp the total grasp force 0 -> ``max_force`` [N] in ``steps`` steps; one equilibrium per step.

    ``on_step(step_index, force, equilibrium)`` is called for every step, in order, once all grasps have
    reached it (e.g. to write fields). Problems that fail (no equilibrium) are flagged in ``status`` and stay
    flagged for later steps. Each grasp goes on to its next force step as soon as it has reached the current
    one (:meth:`fem.QuasiStaticSolver.solve_sequence`): the same equilibria as ``barrier=True`` (one
    :meth:`~fem.QuasiStaticSolver.solve` per step, the whole batch waiting at every step for its slowest
    grasp), without the wait.
    """
    if not np.isfinite(max_force) or max_force <= 0:
        raise ValueError(f"max_force must be a positive force in newtons, got {max_force!r}")
    forces = [max_force * s / steps for s in range(1, steps + 1)]
    if not barrier:

        def reached(k: int, eq: fem.Equilibrium) -> None:
            if on_step is not None:
                on_step(k, forces[k], eq)

        levels = [{GRIP_DOF: force} for force in forces]
        return solver.solve_sequence(levels, on_level=reached, progress=progress)
    out = []
    it = range(steps)
    if progress:
        from tqdm.auto import tqdm

        it = tqdm(it, desc=f"squeeze 0-{max_force:g} N", unit="step", leave=False)
    for k in it:
        eq = solver.solve(targets={GRIP_DOF: forces[k]})
        if on_step is not None:
            on_step(k, forces[k], eq)
        out.append(eq)
    return out
