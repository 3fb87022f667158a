"""Quasi-static equilibrium of a deformable object touched by rigid bodies, for B problems at once.

Every problem minimizes the incremental potential over the vertex displacements u and the travels of
its force-controlled bodies,

    Pi(u, t) = sum_e V_e Psi(F_e) + sum_contacts [E_n + D] - sum_i f_i . u_i - sum_d F_d t_d - G(V(u)),

(elasticity, penalty contact, lagged Coulomb friction, dead body loads, prescribed actuator forces,
gas pressure on a cavity of volume V; see elasticity.py, contact.py, loads.py, pressure.py). Its
stationary points are the equilibria: elastic forces balance contact, friction, body and pressure
forces, and each force-controlled body presses with its prescribed force.

Newton's method: assemble the gradient and the positive semi-definite Hessian, solve H du = -g with
a Krylov solver (batched block-Jacobi CG, Warp) or a sparse direct solver (a closed gas cavity adds a
dense rank-one term, applied by Sherman-Morrison with a second solve), then an Armijo
backtracking line search on Pi per problem, with the step capped so no vertex moves more than a
fraction of the object size per iteration. A tiny diagonal shift handles floating rigid modes
without changing the solution. The friction normal forces and normals are re-lagged at every
iteration from the current state, so a converged state satisfies Coulomb's law with its own normal
forces.

Load stepping: a ``solve`` call moves every problem from its current loads/targets to new ones. If
Newton fails for a problem, its increment is halved (per problem) and retried from the last
converged state; after ``max_load_bisections`` halvings the problem is flagged NOT_CONVERGED. A
problem whose object moves more than ``escape_fraction`` of its size in one increment has no
equilibrium near its last state (it slips out, falls, or loses contact) and is flagged ESCAPED.
Flags are sticky until :meth:`QuasiStaticSolver.reset`; flagged problems are never returned as answers.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass

import numpy as np
import warp as wp
from scipy.spatial.transform import Rotation

from . import contact as ck
from . import elasticity as ek
from . import kernels as kk
from . import pressure as pk
from .bodies import SHAPE_KIND, BodyError, Capsule, RigidBody, Sphere, TriangleMesh, check_rigid_transform
from .loads import BodyLoad
from .material import MATERIAL_MODELS, Material
from .mesh import TetMesh
from .pressure import PressureLoad, PressureSurface
from .results import Equilibrium, SolveStatus
from .self_contact import SELF_CONTACT_MODELS, SelfContact
from .system import BatchedSystem, BlockPattern

__all__ = ["SolverOptions", "QuasiStaticSolver"]

log = logging.getLogger(__name__)


LINEAR_SOLVERS = ("auto", "cg", "amg", "direct", "dense", "banded", "dense_banded")
# the linear solvers that factor each problem's Hessian (exact; factors can be kept for chord Newton)
FACTORIZING_SOLVERS = ("direct", "dense", "banded", "dense_banded")
# the linear solvers that solve with self-contact's vertex-triangle couplings (outside the block pattern):
# "direct" and "dense" add them to the matrix they factor, "banded" (and "dense_banded") factors the
# pattern and adds them by a low-rank update of its solutions (BatchedSystem._solve_coupled);
# CG and AMG would see only the pattern's blocks, with which Newton does not converge (two pressed blocks:
# 4400 iterations for the first contact increment with "amg", or "banded" before session 45, 46 for the
# whole press with the couplings)
SELF_CONTACT_SOLVERS = ("direct", "dense", "banded", "dense_banded")
# Levenberg-Marquardt damping of a rejected exact-Hessian step, in units of E h on the vertex diagonal:
# it starts at LM_START, x10 per rejection up to LM_MAX, /3 per accepted full step, dropped below LM_MIN
LM_START, LM_MAX, LM_MIN = 1e-3, 0.1, 1e-6
# "auto" factors problems densely up to these many unknowns: on CUDA 4000 vertices (1.2 GB per factor);
# on the CPU 300 vertices, where dense and AMG-CG break even (2-core CPU, 4 squeeze ramps x 10 steps: 125
# vertices 2.2 vs 5.2 s (12 ramps x 8), 343 vertices 4.7 vs 4.1 s, 729 vertices 22.0 vs 9.1 s)
DENSE_AUTO_MAX_UNKNOWNS = {"cuda": 12000, "cpu": 900}
# dense factorizations kept for reuse (SolverOptions.max_factor_reuse) may fill at most this fraction of a
# CUDA device's memory; a larger batch is an error rather than a silent switch to plain Newton, which would
# make a problem's answer depend on the size of its batch
DENSE_KEPT_FACTORS_MAX_MEMORY_FRACTION = 0.5
# SolverOptions.max_factor_reuse when None, by device (CPU, CUDA): on the H100 the chord steps did not pay
# (100 x 50 squeeze of the 960-vertex box at 200 kPa, dense: 123.2 s with reuse 4 against 120.2 s without,
# 34.6k instead of 42.2k factorizations, and 98 of 100 grasps converged against 100: the two hardest ran out
# of their Newton budget); on the CPU a factorization costs far more than the triangular solves (see
# SolverOptions)
MAX_FACTOR_REUSE_DEFAULT = {False: 4, True: 0}
# SolverOptions.line_search_trials when None, by device (CPU, CUDA): trial step lengths per energy pass
LINE_SEARCH_TRIALS_DEFAULT = {False: 1, True: 8}


#: share of a problem's Newton budget (``max_newton_per_solve``; ``max_newton_first_step`` in its first load
#: step) after which the proximal loop of ``stabilization_relax`` gives up (the rest is left to the bisection
#: of the failed increment)
RELAX_BUDGET_SHARE = 1.0
#: smallest fraction of the increment stabilization springs that ``stabilization_relax_decay`` weakens
#: them to
RELAX_SPRING_FLOOR = 1e-3
#: with self-contact, an increment starts from the last converged state instead of the predictor's
#: extrapolation where that would put a surface vertex deeper than this fraction of the self-contact depth
#: (``self_contact.SELF_CONTACT_DEPTH`` h) behind the surface (``QuasiStaticSolver._start_increment``)
PREDICTED_SELF_PENETRATION = 0.5


def _check_int(name: str, value, minimum: int) -> None:
    """A SolverOptions field that is an integer (not a bool) >= ``minimum``."""
    if isinstance(value, bool) or not (isinstance(value, (int, np.integer)) and value >= minimum):
        raise ValueError(f"SolverOptions.{name} must be an int >= {minimum}, got {value!r}")


def _check_optional_int(name: str, value, minimum: int) -> None:
    """A SolverOptions field that is None (the default) or an integer (not a bool) >= ``minimum``."""
    if value is not None and (
        isinstance(value, bool) or not (isinstance(value, (int, np.integer)) and value >= minimum)
    ):
        raise ValueError(f"SolverOptions.{name} must be None or an integer >= {minimum}, got {value!r}")


@dataclass(frozen=True)
class SolverOptions:
    """Numerical settings of :class:`QuasiStaticSolver` (defaults suit E from 1e4 to 1e9 Pa).

    Args:
        contact_stiffness: kappa, penalty pressure stiffness in units of E / h, h the median surface edge
            length: a contact pressure p penetrates ((p / E) / kappa + zeta / 2) h, reported as
            ``max_penetration``.
        contact_smoothing: zeta, onset width of the C2 penalty in units of h (see ``contact.py``).
        friction_stick_slip: c, smallest stick zone of a frictional contact in units of its vertex size h_i:
            the tangential stick stiffness is min(k_i, mu N / (c h_i)) instead of the normal penalty
            stiffness k_i (0: off; see ``contact.py``). Slip thresholds (the Coulomb limit) are unchanged;
            sticking vertices may shift by up to c h_i before they slide.
        rtol: a problem has converged when every free residual force component is below
            ``rtol`` times the largest elastic, body-load or actuator force component.
        max_newton_iterations: per load increment before it is halved.
        max_load_bisections: a problem is flagged when its failing increment would drop below 2^-n of the
            requested change (or after 4 n failed increments in one call).
        linear_solver: "cg" (batched block-Jacobi CG in Warp, on the solver's device), "amg" (CG with a
            smoothed-aggregation multigrid preconditioner, pyamg, on the host), "direct" (SuperLU on the
            host), "dense" (batched dense Cholesky on the solver's device through PyTorch/cuSOLVER, exact;
            memory 3 x (3R)^2 x 8 bytes per problem in flight), "banded" (batched block-tridiagonal
            Cholesky of the breadth-first level ordering on the solver's device, exact; a fraction of
            the dense solver's flops and memory, see ``block_tridiagonal.py``), "dense_banded" (per linear
            solve: dense when fewer than ``banded_min_problems`` problems need a new factorization, banded
            otherwise; :meth:`BatchedSystem.solve_dense_banded`) or "auto" (dense up to 900
            unknowns per problem on the CPU and 12000 on CUDA; above that amg on the CPU, cg on CUDA).
        banded_min_problems: the "dense_banded" solver factors this many problems or more at once with the
            banded solver, fewer with the dense one. 4 since the banded substitution became batched products
            (session 33, one H100, two pairs of runs in one lease: FEM benchmark 53.3 / 53.3 s against 57.9
            / 53.0 s with 12, streamed poke benchmark 80.2 / 79.7 s against 87.8 / 83.7 s; 8: 52.3 and
            88.9 s); 12 had been the fastest of 4-32 with triangular-solve substitutions (session 28).
        factor_streams: CUDA streams on which the "dense" solver (and "dense_banded" below
            ``banded_min_problems``) factors a few problems side by side; 1: one after another (the CPU
            always does). 3 (session 46, one H200): the FEM benchmark's three slowest grasps alone, 20
            steps, 6.97 -> 5.91 s (GPU busy 5.9 -> 5.2 ms per Newton pass); the whole benchmark unchanged
            within its run-to-run spread (median 32.2 s of 7 runs with 1, 32.4 s of 9 with 3;
            ``benchmarks/fem_cuda_factor_streams_h200_s46.json``).
        factor_graphs: fraction of the GPU's memory that CUDA graphs of the "banded" (and "dense_banded")
            solver's block-Cholesky factorization may hold: one graph per batch size class, captured on
            first use and replayed after, so that the host launches a factorization's ~650 kernels once
            (``block_tridiagonal.FactorGraphs``; 21 MB per problem of each size class on the FEM
            benchmark's box); batches above 64 problems are factored eagerly (GPU-bound: padding costs
            more than the launches). 0: factor eagerly (the CPU always does). Solutions equal the eager
            ones to round-off. 0.1 (session 47, one H200, ``benchmarks/fem_cuda_factor_graphs_h200_s47.md``):
            the FEM benchmark's bulk (100 grasps, 5 steps) median 6.79 s against 8.04 s eager; the whole
            benchmark, graphs for every batch size, median 32.1 s against 34.2 s (10 pairs); 32 tactile
            poke paths 26.4 s against 33.9 s (one pair). Session 48, another H200 lease with a faster host:
            the whole benchmark with this rule median 29.96 s against 29.48 s eager (4 pairs, eager faster
            in 3; ``benchmarks/fem_cuda_whole_graphs_ab_host_profile_h200_s48.md``): the gain depends on the
            host.
        cg_rtol, cg_max_iterations: tightest Krylov tolerance (relative to the right-hand side) and cap; the
            tolerance of each Newton step follows the Eisenstat-Walker forcing term (inexact Newton).
        max_step_fraction: largest vertex or travel motion per Newton iteration, as a fraction of the mesh
            bounding-box diagonal.
        friction_relag_iterations: Newton iterations of an increment that re-lag the friction normal forces
            before they are frozen; max_friction_relags: further re-lags allowed to reach a state whose normal
            forces equal its lagged ones.
        relag_friction_on_retry: a load increment that failed is retried (halved) with the friction normal
            forces re-lagged at every Newton iteration, never frozen (a converged state is then consistent
            with its own normal forces by construction): where a few contact vertices carry the load (the
            pads on a stiff curved fTetWild mesh), frozen lags and their re-lag cycles never settle. True
            (or 1): from the first failed attempt of a load step on; an integer k: from the k-th on (the
            earlier retries keep the frozen lags); False (or 0): never.
        friction_rtol: a converged state is consistent with its lagged normal forces when every contact's
            friction capacity error ``mu (|N - N_lag| + N |n - n_lag|)`` is below the residual tolerance
            (default, ``friction_rtol = 0``: Coulomb holds per contact to the Newton tolerance), or when
            their sum is below ``friction_rtol sum mu N`` (the total friction capacity, and every
            contact's, exact to ``friction_rtol`` of the total). The lag fixed point contracts only about
            2x per re-lag (measured on a tilted Franka grasp), so the strict test costs a dozen re-lags of
            ~10 Newton iterations each per load step there; 1e-3 cut that grasp's iterations by 30 %.
        friction_relaxation: re-lags of a stale converged state extrapolate the normal forces by Aitken's
            dynamic relaxation instead of copying them (see ``_relag_friction``); False: plain fixed-point
            re-lags.
        friction_lag_check: a problem iterating with frozen friction lags has its lag consistency checked
            already once its residual is below ``friction_lag_check`` times the tolerance (not only at
            convergence), and is re-lagged at once where some contact's friction capacity error exceeds 10
            times its residual (the normal forces move by about the residual in the last iterations, so
            such a state would converge only to be found inconsistent and re-lagged); the re-lag is
            Aitken-extrapolated like a converged state's (``friction_relaxation``). The converged state is
            checked as before, so the answer's tolerance is unchanged; 1 (default): only at convergence.
            Measured (session 34, 2-core CPU) and not yet a default: the FEM benchmark's slowest grasp alone
            ("direct", plain Newton as on CUDA, 0-15 N in 50 steps) 2301 Newton iterations with 1, 2036 with
            100, 1712 with 1000, 1802 with 1e4 (final displacements within 2.8e-4 of the largest: another
            friction path); 4 poke paths of the membrane 1807 -> 1488 Newton steps with 1000 (one of 20 base
            forces moved by 1.3 %). But with 100 or 1000 the squeeze path's first step on a stiff fTetWild
            cylinder (4 grasps touching single vertices, 10 MPa) fails 1-2 grasps that converge with 1;
            without the extrapolation of early re-lags it does not, but the slow grasp then takes 2367
            iterations. Not timed on a GPU.
        max_newton_per_solve: Newton iteration budget of one problem in one :meth:`solve` call, over all its
            load increments (0: none). A problem that spends it is flagged NOT_CONVERGED at its last
            converged state. Batches advance in lockstep, so one hard problem (a tilted grasp whose friction
            keeps re-lagging: measured up to 2000 iterations per load step) otherwise holds up all others;
            data generators set a budget and drop the flagged problems.
        max_newton_first_step: Newton iteration budget of a problem's first load step since its rest state
            (None, the default: ``max_newton_per_solve``; 0: none), over all its load increments: the first
            :meth:`solve` call or :meth:`solve_sequence` / :meth:`solve_stream` level after the solver was
            built, :meth:`reset`, or the problem was copied (:meth:`copy_state_from`) from one that has not
            finished a load step yet. Later load steps keep ``max_newton_per_solve``. A stiff curved object
            must still roll or slide into the grasp in a squeeze ramp's first force step, through the
            proximal loop of ``stabilization_relax`` (which counts towards this budget, at
            ``RELAX_BUDGET_SHARE``); the later steps of the ramp mostly start from a settled grip (measured on
            the 2-core CPU, ``benchmarks/squeeze_first_step_budget_cpu.md``). A problem counts a load step as
            finished once it has reached the step's end (converged), so a problem flagged in its first step
            never leaves it.
        force_maximum_runaway: R, early flag of a force ramp that passed a force maximum of its equilibrium
            path (0: off, the default). A force ramp cannot pass a limit point: every increment beyond it runs
            away and fails, and plain halving spends the rest of the problem's Newton budget on ever smaller
            increments before NOT_CONVERGED. A failed (NOT_CONVERGED) increment that raised the force of a
            force-controlled dof "ran away" when its last Newton iterate moved that dof's travel more than R
            times what the secant stiffness of the problem's last converged increment (its force change over
            its travel change, same direction) predicts for the increment's force change; after
            ``force_maximum_attempts`` such runaways within one load step (one ``solve`` call or one level of
            :meth:`QuasiStaticSolver.solve_sequence`) the problem is flagged FORCE_MAXIMUM at its last
            converged state instead of being bisected further. A problem with no such converged increment (a
            ramp's first step, after ``reset`` or a copied rest state) is never flagged so; one that converges
            never meets the test, so its path and answer do not change (bit for bit). Measured (session 38,
            2-core CPU, "direct", ``benchmarks/squeeze_force_maximum_cpu.md``) on squeeze ramps of the
            268-vertex fTetWild cube (0-15 N in 50 steps, grasps 0, 4, ..., 96 of 100): at E = 10 kPa 10 of
            25 ramps stop at the force maximum (after 3.3-10.8 N), where the failing step's 5 failed attempts
            of 40 iterations spend the 200-iteration budget: 36 % of those ramps' Newton iterations and time.
            The first two failed attempts of each such step ran the travel 5-21 times past the secant's
            prediction (1.0-3.6 mm); the 28 judged failed attempts of 153 converging ramps (the cube at 10
            kPa, 100 kPa and 10 MPa, its 921-vertex data-path mesh at 10 kPa; a cone, a capsule and a
            cylinder at 10 MPa and 100 kPa, tilted and curved first contacts) stayed within 0.99 times it,
            and so did stalls that are no force maximum (they stay NOT_CONVERGED). With R = 3 and 2 attempts
            the 10 ramps are flagged FORCE_MAXIMUM at the same load step, their failing steps cost 80-86
            instead of 200-228 Newton iterations, 22 % fewer in all (5920 -> 4619; 921-vertex cube: 2
            ramps, 15 %), every converging ramp unchanged; 1 attempt would save 29 %. The secant stiffness
            itself does not announce the maximum (at the last converged step 0.47-1.0 times its largest
            value on the ramp): the cube gives way abruptly.
        force_maximum_attempts: runaway failed increments of one load step that flag FORCE_MAXIMUM (>= 1;
            see ``force_maximum_runaway``).
        force_maximum_snap: S (0: off, the default), what a problem does once ``force_maximum_attempts``
            runaways were counted in a load step: instead of being flagged FORCE_MAXIMUM at once it retries
            the failing increment (not halved, friction lags frozen after the first iterations as in a first
            attempt) with up to S Newton iterations per solve, and so does every later increment of the
            problem, whose Newton budget per load step (``max_newton_per_solve``) grows by S. A runaway need
            not end the path: past a limit point of its branch the path may *snap*, jump at the same force to
            another equilibrium that carries more load; the runaway attempts were on their way there and
            stopped after ``max_newton_iterations``. If the retry fails the problem is flagged FORCE_MAXIMUM
            as before; if the load step is reached, the problem goes on and ``Equilibrium.snaps`` counts the
            step. Ramps that never run away twice in a step are unchanged bit for bit. Measured (session 40,
            2-core CPU, ``benchmarks/squeeze_soft_failures_cpu.md``): soft squeeze ramps flagged at 6.0 N
            (cuboid_70x35x20, 10 kPa) and 11.7 N (cylinder_r20_h40, 21.5 kPa) reach 15 N with S = 200, the
            object turned and slid between the pads by millimetres, but the states after the jump pass
            through themselves (the FEM has no self-contact; ``TetMesh.surface_vertices_inside``): there it
            buys nothing, and the squeeze path keeps it off.
        escape_fraction: object motion within one increment, as a fraction of the diagonal, that flags
            the problem ESCAPED (no equilibrium).
        regularization: diagonal shift relative to E h per vertex (removes floating rigid modes).
        stabilization: increment stabilization ``s`` (0: off): every vertex is tied to its position at the
            start of the load increment by a spring ``c_i = s E h_i`` (``h_i`` the vertex size), energy
            ``c_i |u_i - u_ref_i|^2 / 2``. It makes the first increments of a grasp well posed while the
            contacts that will hold the object are still points with no friction capacity (a pad tilted
            against an edge or corner: the object's rigid modes are otherwise free and Newton's steps
            along them unbounded). The price is a spurious force ``c_i (u_i - u_ref_i)`` at equilibrium;
            its largest value is reported as ``Equilibrium.stabilization_force`` (compare it with the loads).
        stabilization_release: with ``stabilization`` > 0, a load increment that converged stabilized is
            continued by Newton without the springs, from that state, and accepted only if this converges
            (else it is bisected like any failed increment): the springs guide the path while the contacts
            establish themselves (as a static FE code's contact stabilization, ramped off at the end of the
            step) and the answer is an exact equilibrium, ``stabilization_force`` 0.
        stabilization_relax: with ``stabilization_release``, the most re-referenced stabilized solves of one
            load increment after its released solve failed (0, the default: none, the increment is bisected at
            once). Where a stiff object must still roll or slide into the grasp (a pad's first contact on a
            curved surface), the stabilized increment converges but the released Newton solve stalls on the
            near-free rigid mode the springs held. With this option the problem goes back to the stabilized
            solution and repeats the increment's stabilized solve, each time with the springs' reference and
            the friction anchor (reference positions, stick stretches, body placements) moved to the last
            converged stabilized solution, as a commit would move them (a proximal-point iteration; the
            increment's start is kept as the restore point and the predictor's origin), until the springs'
            largest force ``max_i c_i |u_i - u_spring_i|`` is no more than the Newton tolerance; then the
            springs are released again (an exact equilibrium is still required). It gives up (the increment is
            restored and bisected as before) after this many solves, when one fails, or when the problem has
            spent ``RELAX_BUDGET_SHARE`` (1) of its Newton budget (``max_newton_per_solve``): the relax solves
            count towards it. Problems whose release converges are untouched, bit for bit. Measured (session
            38, 2-core CPU, "direct", squeeze defaults, ``benchmarks/squeeze_relax_cpu.md``): the first force
            step (0.3 N) of the 997-vertex fTetWild torus at 10 MPa, grasps 20-59: 5 of the 16 that fail
            converge with 40 and the 200-iteration budget (134-149 Newton iterations; 29 instead of 24 of 40,
            4406 instead of 5034 Newton iterations in all), 22 of the 24 others bit-identical (two saved by
            bisection before converge on another path, turned about the grasp axis); grasps 6 and 7 need 46
            and 60 solves, 599 and 1150 Newton iterations (budget 2000) and end ~0.9 mm further on, where the
            proximal steps shrink x0.9 per solve; grasps 17 and 18 creep (springs' force flat at ~2e-5 N over
            389 solves) and still fail. With the springs re-referenced but the friction anchor kept at the
            increment's start, grasp 6 slid at a constant springs' force and its 8th solve failed. On squeeze
            ramps of the 268-vertex cube (25 grasps, 0-15 N in 50 steps) every ramp without a failed release
            is bit-identical at 10 kPa and 100 kPa (25 of 25: none relaxes) and 10 MPa (21 of 25); at 10 MPa
            grasp 4 converges (it failed its first step), two converge either way with fewer iterations (on
            another path), and grasp 96, which plain bisection saves after a failed release, spends its budget
            in the loop and fails (``RELAX_BUDGET_SHARE`` 0.5 saves 96 and loses 4; 0.75 the reverse).
        stabilization_relax_decay: d in (0, 1], the springs' fraction kept from one proximal solve of
            ``stabilization_relax`` to the next (1, the default: constant springs). Each converged proximal
            solve that still needs another weakens the problem's springs by d (down to ``RELAX_SPRING_FLOOR``
            of the full springs); a proximal solve with weakened springs that fails goes back to the last
            converged one with springs 1 / d^2 stiffer (capped at full) instead of giving up. A proximal-point
            iteration whose regularization shrinks converges superlinearly where constant springs creep: the
            springs' force, the released problem's residual, is measured with the springs of the solve.
            Measured (session 39, 2-core CPU, "direct", squeeze defaults,
            ``benchmarks/squeeze_relax_cpu.md``): the first force step of the 1023-vertex fTetWild
            annulus_ro45_ri35_h20 at 4.64 MPa, grasp 3: constant springs reach the equilibrium (0.38 mm
            further on) in 176 solves and 847 Newton iterations (no budget), d = 0.5 in 9 solves and 320, d =
            0.25 in 6 and 281.
        exact_hessian: once a problem's Newton step is accepted in full and lowers the residual, its next
            iterations use the exact elastic Hessian (signed element eigenvalues) instead of the PSD-projected
            one: near a stable equilibrium the assembled Hessian is positive definite even where compressed
            elements are not. Measured on a fingertip dimpling the membrane: 8 % fewer Newton iterations (the
            slow convergence there has another cause, still open). A step that is not a descent direction
            or needs backtracking (a step only shortened to ``max_step_fraction`` is not rejected) is
            retried with Levenberg-Marquardt damping on the exact Hessian, ``LM_START`` = 1e-3 to
            ``LM_MAX`` = 0.1 times E h on the diagonal (x10 per rejection, /3 per accepted full step, dropped
            below ``LM_MIN`` = 1e-6); past ``LM_MAX`` the problem returns to the projected Hessian for the
            rest of the increment. Near a crease of a soft solid (a near-zero negative eigenvalue) the
            projected Hessian overestimates the curvature and Newton crawls, while the damped exact step
            converges. The damping shrinks after every accepted full step, not only those that lower the
            residual: a body sliding at the friction limit keeps its residual while its energy falls, and a
            fixed damping would make it crawl instead of being flagged ESCAPED. With a factorizing solver
            ("dense", "banded", "dense_banded") an exact Hessian whose Cholesky factorization breaks down
            (not positive definite) is damped at once, without a step (``BatchedSystem.report_indefinite``),
            instead of being solved by LU: of 8 such LU steps in 4 poke paths of the membrane (2-core CPU), 6
            were rejected by the line search and 1 cut back. Measured on one H100 (192 poke paths streamed
            through 128 problems, dense_banded, one pair of runs in one lease, not profiled): 83.7 -> 64.4 s
            (what it removes: the block-LU factorizations and their per-block LU substitutions); FEM
            benchmark 53.8 -> 52.0 s.
        max_factor_reuse: chord (modified) Newton for the factorizing linear solvers (FACTORIZING_SOLVERS):
            a problem's factorization serves up to this many further Newton steps (also across its load
            increments) before it is factored anew; 0: every step factors its own Hessian (plain Newton);
            None (default): 4 on the CPU, 0 on CUDA (``MAX_FACTOR_REUSE_DEFAULT``: measured on an H100 it
            saved no time and cost 2 of 100 grasps their convergence).
            A stale factorization of a positive definite Hessian still gives a descent direction, which the
            line search keeps safe; convergence is tested on the true residual, so the answer keeps the
            Newton tolerance. A problem refactors, from its own data only (a problem's answer does not depend
            on its batch), when its last step contracted the residual by less than
            ``factor_reuse_contraction``, when a step with a stale factorization was rejected or cut back by
            the line search (the step is then redone with a fresh one), when its Levenberg-Marquardt damping
            changed, after a failed load increment, and on :meth:`QuasiStaticSolver.reset`,
            ``set_material`` and ``set_body_pose``. Measured on squeeze ramps of the 960-vertex Neo-Hookean
            box (0-15 N in 50 steps, 2-core CPU, plain Newton -> default): 8 grasps at E = 200 kPa, "direct":
            1104 -> 583 factorizations, 1104 -> 1362 Newton iterations (lockstep 381 -> 409), all 8 converged;
            at 20 kPa 3605 -> 2972 factorizations, 3605 -> 4031 iterations, the same 5 of 8 converged; 2
            grasps at 200 kPa, "dense": 200 -> 66 factorizations, 200 -> 244 iterations, 104 -> 34 s. Final
            displacements differ by at most 5e-5 (200 kPa) and 5e-4 (20 kPa, friction-path dependent) of the
            largest one. With "dense", one (3R)^2 float64 factor per problem stays allocated (2883
            unknowns: 66 MB; on CUDA at most half the device memory, else an error). Krylov solvers ("cg",
            "amg") ignore it. On the H100 (dense, 100 grasps at 200 kPa) reuse 4 took 123.2 s against 120.2 s
            with 34.6k instead of 42.2k factorizations but 49.9k instead of 42.2k Newton iterations: the
            per-iteration assembly, line search and batched triangular solves dominate there, and the extra
            iterations exhausted the 200-iteration budget of two tilted grasps.
        factor_reuse_contraction: a problem keeps its factorization for the next step only while its last
            step divided the residual (max norm) by at least 1 / ``factor_reuse_contraction``, in (0, 1).
            0.5 instead of 0.25 cut the factorizations of a soft (20 kPa) grasp less than the extra Newton
            iterations it cost (19 vs 10 factorizations with plain Newton on tests' 4-step grasp).
        line_search_trials: step lengths whose energies the Armijo line search evaluates in one pass:
            the current state (slot 0 of the first pass) and the next halvings ``a, a/2, a/4, ...`` side by
            side in one set of launches and one device synchronization, instead of one halving at a time.
            The accepted step is the one plain backtracking accepts (the largest of the halvings that passes
            the Armijo test), so the result does not depend on it. None (default): 8 on CUDA, where a pass
            over a few trial states costs about what one does (the launches and host synchronizations of
            a Newton iteration dominate the tail of a lockstep batch), 1 on the CPU, where every trial
            costs its full energy evaluation (``LINE_SEARCH_TRIALS_DEFAULT``).
        query_distance: search radius [m] of triangle-mesh bodies' signed distance queries.
        record_tet_stress: keep the per-tet Cauchy stress in results (B x M x 9 floats).
        contact_subdivisions: n, sub-vertex contact: the contact points are the vertices of the uniform
            n-subdivision of every surface triangle (``contact.surface_contact_points``), each with its
            lumped share of the subdivided surface area, instead of the surface vertices alone (1, the
            default: vertex contact, bit for bit as before). A rigid body narrower than the vertex spacing
            (the membrane's 10 mm fingertip) no longer slips between vertices into the triangles. The
            pressure stiffness kappa E / h and the penetration tolerance are unchanged; contact slots,
            friction lags and stick anchors are per (problem, point, body); results stay per surface vertex
            (point forces lumped with the barycentric weights). Cost: ~n^2 times the contact points (see
            ``contact.py``).
        self_contact: s, self-contact of the object's surface (``self_contact.py``; frictionless unless
            ``self_contact_friction``): every surface vertex is pushed out of the nearest facing triangle
            of the object's own surface that it is not near at rest, with the rigid contact's penalty law at
            s times its stiffness (s = 1: the same pressure stiffness kappa E / h and penetration tolerance).
            0 (default): off, bit for bit as before. Pairs are found per Newton iteration with one Warp BVH
            per problem. Its Hessian couples vertices outside the FEM block pattern: needs linear_solver
            "direct", "dense", "banded" or "dense_banded" ("auto" picks "direct" where it would pick an
            iterative solver), which solve with those couplings; CG and AMG would not converge
            (``SELF_CONTACT_SOLVERS``).
        self_contact_model: how a vertex's penetration of the surface is measured (``self_contact.py``):
            "prism" (default): the depth below the least deep candidate triangle whose prism holds the
            vertex; "feature": the distance to the nearest candidate triangle, closed (edges and corners),
            that the vertex lies behind at its closest point and behind the triangles across the edges that
            point lies on (continuous across triangle boundaries: a vertex in the wedge behind a concave
            crease is held at its distance from the crease, where "prism" lets it go). Measured worse
            than "prism" on the data path's folding and collapsing objects (benchmarks/
            fem_self_contact_cpu.md, session 43): an option, not the default. "barrier": IPC's log
            barrier on the unsigned distances of every near vertex-triangle and edge-edge pair (activation
            distance ``SELF_CONTACT_GAP`` = 0.05 h), the line search bounded so that no pair's distance
            reaches zero: continuous everywhere, never penetrating (parts meet 0.05 h early); the thin
            ring's four CPU ramps all reach 15 N ("prism": two), at ~1.5-1.8x the time per Newton
            iteration (``benchmarks/fem_self_contact_barrier_s50.md``). Refuses a surface within 0.05 h of
            itself at rest.
        self_contact_friction: mu, Coulomb friction of the surface on itself (model "barrier" only; 0, the
            default: frictionless, bit for bit as before): IPC's lagged friction (``self_contact.py``): the
            barrier pairs closer than d^ at an increment's start, slips measured from there, a smoothed
            Coulomb potential whose force rises with the tangential slip to mu lambda over
            ``SELF_CONTACT_FRICTION_SLIP`` = 0.01 h; the normal forces re-lagged like the rigid contact's and
            checked for consistency at convergence (re-lagged until every pair's capacity error is below
            the tolerance).
    """

    contact_stiffness: float = 1000.0
    contact_smoothing: float = 0.0
    friction_stick_slip: float = 0.0
    rtol: float = 1e-7
    max_newton_iterations: int = 40
    max_load_bisections: int = 10
    linear_solver: str = "auto"
    banded_min_problems: int = 4
    factor_streams: int = 3
    factor_graphs: float = 0.1
    cg_rtol: float = 1e-8
    cg_max_iterations: int = 5000
    max_step_fraction: float = 0.1
    friction_relag_iterations: int = 4
    max_friction_relags: int = 8
    relag_friction_on_retry: bool | int = False
    friction_rtol: float = 0.0
    friction_relaxation: bool = True
    friction_lag_check: float = 1.0
    max_newton_per_solve: int = 0
    max_newton_first_step: int | None = None
    force_maximum_runaway: float = 0.0
    force_maximum_attempts: int = 2
    force_maximum_snap: int = 0
    escape_fraction: float = 0.5
    regularization: float = 1e-10
    stabilization: float = 0.0
    stabilization_release: bool = False
    stabilization_relax: int = 0
    stabilization_relax_decay: float = 1.0
    exact_hessian: bool = True
    max_factor_reuse: int | None = None
    factor_reuse_contraction: float = 0.25
    line_search_trials: int | None = None
    query_distance: float = 1.0
    record_tet_stress: bool = False
    contact_subdivisions: int = 1
    self_contact: float = 0.0
    self_contact_model: str = "prism"
    self_contact_friction: float = 0.0

    def __post_init__(self):
        if self.linear_solver not in LINEAR_SOLVERS:
            raise ValueError(
                f"linear_solver must be one of {', '.join(LINEAR_SOLVERS)}, got {self.linear_solver!r}"
            )
        if not (isinstance(self.banded_min_problems, (int, np.integer)) and self.banded_min_problems >= 1):
            raise ValueError(
                f"SolverOptions.banded_min_problems must be an int >= 1, got {self.banded_min_problems!r}"
            )
        _check_optional_int("line_search_trials", self.line_search_trials, 1)
        _check_int("factor_streams", self.factor_streams, 1)
        fg = self.factor_graphs
        if not (
            isinstance(fg, (int, float, np.integer, np.floating))
            and not isinstance(fg, bool)
            and 0 <= fg <= 1
        ):
            raise ValueError(f"SolverOptions.factor_graphs must be a fraction in [0, 1], got {fg!r}")
        _check_int("contact_subdivisions", self.contact_subdivisions, 1)
        sc = self.self_contact
        if not (isinstance(sc, (bool, int, float, np.integer, np.floating)) and np.isfinite(sc) and sc >= 0):
            raise ValueError(
                f"SolverOptions.self_contact must be a finite stiffness scale >= 0 (0: off), got {sc!r}"
            )
        if self.self_contact_model not in SELF_CONTACT_MODELS:
            raise ValueError(
                f"SolverOptions.self_contact_model must be one of {', '.join(SELF_CONTACT_MODELS)}, got "
                f"{self.self_contact_model!r}"
            )
        mu = self.self_contact_friction
        if (
            not (
                isinstance(mu, (int, float, np.integer, np.floating))
                and not isinstance(mu, bool)
                and np.isfinite(mu)
            )
            or mu < 0
        ):
            raise ValueError(
                f"SolverOptions.self_contact_friction must be a finite friction coefficient >= 0 (0: "
                f"frictionless), got {mu!r}"
            )
        if mu > 0 and (sc == 0 or self.self_contact_model != "barrier"):
            raise ValueError(
                "SolverOptions.self_contact_friction needs self_contact > 0 and self_contact_model 'barrier' "
                f"(the friction pairs are the barrier's), got self_contact={sc!r}, self_contact_model="
                f"{self.self_contact_model!r}"
            )
        if sc > 0 and self.linear_solver not in ("auto", *SELF_CONTACT_SOLVERS):
            # refused here, before a caller (the grasp generator) writes anything
            raise ValueError(
                f"SolverOptions.self_contact needs linear_solver 'direct', 'dense', 'banded', "
                f"'dense_banded' or 'auto', got {self.linear_solver!r}: self-contact couples vertices "
                "outside the FEM block pattern, which only those solvers solve with (without the couplings "
                "Newton does not converge)"
            )
        if not (np.isfinite(self.stabilization) and self.stabilization >= 0):
            raise ValueError(f"SolverOptions.stabilization must be >= 0, got {self.stabilization!r}")
        if self.stabilization_release and self.stabilization == 0:
            raise ValueError(
                "SolverOptions.stabilization_release needs stabilization > 0 (no springs to release)"
            )
        relax = self.stabilization_relax
        if isinstance(relax, bool) or not (isinstance(relax, (int, np.integer)) and relax >= 0):
            raise ValueError(f"SolverOptions.stabilization_relax must be an int >= 0, got {relax!r}")
        if not (np.isfinite(self.stabilization_relax_decay) and 0 < self.stabilization_relax_decay <= 1):
            raise ValueError(
                "SolverOptions.stabilization_relax_decay must be in (0, 1], "
                f"got {self.stabilization_relax_decay!r}"
            )
        if not (np.isfinite(self.force_maximum_runaway) and self.force_maximum_runaway >= 0):
            raise ValueError(
                f"SolverOptions.force_maximum_runaway must be >= 0, got {self.force_maximum_runaway!r}"
            )
        attempts = self.force_maximum_attempts
        if not (isinstance(attempts, (int, np.integer)) and attempts >= 1):
            raise ValueError(
                "SolverOptions.force_maximum_attempts must be an int >= 1, "
                f"got {self.force_maximum_attempts!r}"
            )
        snap = self.force_maximum_snap
        if isinstance(snap, bool) or not (isinstance(snap, (int, np.integer)) and snap >= 0):
            raise ValueError(f"SolverOptions.force_maximum_snap must be an int >= 0, got {snap!r}")
        if self.max_newton_per_solve < 0:
            raise ValueError(
                f"SolverOptions.max_newton_per_solve must be >= 0, got {self.max_newton_per_solve!r}"
            )
        _check_optional_int("max_newton_first_step", self.max_newton_first_step, 0)
        _check_optional_int("max_factor_reuse", self.max_factor_reuse, 0)
        if not 0 < self.factor_reuse_contraction < 1:
            raise ValueError(
                "SolverOptions.factor_reuse_contraction must be in (0, 1), "
                f"got {self.factor_reuse_contraction!r}"
            )
        if not self.friction_lag_check >= 1:
            raise ValueError(
                f"SolverOptions.friction_lag_check must be >= 1, got {self.friction_lag_check!r}"
            )
        if not 0 <= self.friction_rtol < 1:
            raise ValueError(f"SolverOptions.friction_rtol must be in [0, 1), got {self.friction_rtol!r}")
        relag = self.relag_friction_on_retry
        if not isinstance(relag, (bool, int, np.integer)) or relag < 0:
            raise ValueError(
                "SolverOptions.relag_friction_on_retry must be a bool or the failed attempt (>= 1) from "
                f"which on an increment is retried with re-lagged friction, got {relag!r}"
            )
        for name in ("contact_stiffness", "rtol", "cg_rtol", "max_step_fraction", "escape_fraction"):
            if not getattr(self, name) > 0:
                raise ValueError(f"SolverOptions.{name} must be > 0, got {getattr(self, name)!r}")
        if not 0 <= self.friction_stick_slip < 1:
            raise ValueError(
                f"SolverOptions.friction_stick_slip must be in [0, 1), got {self.friction_stick_slip!r}"
            )
        if not 0 <= self.contact_smoothing < 1:
            raise ValueError(
                f"SolverOptions.contact_smoothing must be in [0, 1), got {self.contact_smoothing!r}"
            )


def pose_change(start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """(..., 6) rigid motion from ``start`` to ``end`` poses (..., 4, 4): translation and rotation vector
    of the relative rotation R_start^T R_end (in the start frame) [m, rad]."""
    if start.size == 0:
        return np.zeros((*start.shape[:-2], 6))
    rel = np.einsum("...ji,...jk->...ik", start[..., :3, :3], end[..., :3, :3])
    rotvec = Rotation.from_matrix(rel.reshape(-1, 3, 3)).as_rotvec().reshape(*rel.shape[:-2], 3)
    return np.concatenate([end[..., :3, 3] - start[..., :3, 3], rotvec], axis=-1)


def interpolate_poses(start: np.ndarray, end: np.ndarray, fraction) -> np.ndarray:
    """Poses a ``fraction`` (per problem, (B,)) of the way from ``start`` to ``end`` (B, K, 4, 4):
    translation linear, rotation R_start exp(fraction log(R_start^T R_end)) (the geodesic)."""
    lam = np.broadcast_to(np.asarray(fraction, dtype=np.float64), start.shape[:1])
    if start.size == 0:
        return start.copy()
    motion = pose_change(start, end)
    w = lam.reshape(-1, *([1] * (motion.ndim - 1)))
    out = start.copy()
    step = Rotation.from_rotvec((w * motion[..., 3:]).reshape(-1, 3)).as_matrix()
    step = step.reshape(*motion.shape[:-1], 3, 3)
    out[..., :3, :3] = start[..., :3, :3] @ step
    out[..., :3, 3] = start[..., :3, 3] + w * motion[..., :3]
    return out


def rigid_body_modes(points: np.ndarray, batch_size: int, num_dofs: int) -> np.ndarray:
    """(B (N + D) 3, 6) translations and infinitesimal rotations of every problem's vertices (the near-null
    space of elasticity, for multigrid); travel rows get the unit translations."""
    n = len(points)
    x = points - points.mean(axis=0)
    modes = np.zeros((n + num_dofs, 3, 6))
    modes[:, [0, 1, 2], [0, 1, 2]] = 1.0
    for k in range(3):  # rotation about axis k: e_k x x
        modes[:n, :, 3 + k] = np.cross(np.eye(3)[k], x)
    return np.tile(modes.reshape(-1, 6), (batch_size, 1))


def _per_problem(value, batch_size: int, name: str) -> np.ndarray:
    try:
        v = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{name} must be a number or {batch_size} numbers, got {value!r}") from e
    if v.ndim == 0:
        v = np.full(batch_size, float(v))
    if v.shape != (batch_size,):
        raise ValueError(f"{name} must be a scalar or have shape ({batch_size},), got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return v


def pinched_vertices(normal_force: np.ndarray, normal: np.ndarray, max_cosine: float = -0.5) -> np.ndarray:
    """(B, S) True where a surface vertex is pressed by two bodies whose normal forces on it oppose
    (cosine of the angle between them below ``max_cosine``), both above 1e-3 of the problem's largest.

    ``normal_force``: (B, S, K) normal contact force of each body on each surface vertex [N];
    ``normal``: (B, S, K, 3) unit directions of those forces. A volumetric object cannot be squeezed at a
    single vertex from both sides: such an equilibrium is a rigid body that slipped between the object's
    vertices (vertex-based contact does not see the edges and faces), with the two forces cancelling and
    the object unstressed. The solver flags it :attr:`SolveStatus.PINCHED`.
    """
    K = normal_force.shape[2]
    pressed = normal_force > 1e-3 * normal_force.max(axis=(1, 2), keepdims=True).clip(min=1e-300)
    out = np.zeros(normal_force.shape[:2], dtype=bool)
    for a in range(K):
        for b in range(a + 1, K):
            cosine = np.einsum("bsi,bsi->bs", normal[:, :, a], normal[:, :, b])
            out |= pressed[:, :, a] & pressed[:, :, b] & (cosine < max_cosine)
    return out


def _problem_view(array: wp.array, batch_size: int, per: int):
    """(batch_size, per, ...) PyTorch view of the first batch_size * per entries of a problem-major Warp
    array (no copy; synchronize Warp's stream before reading what its kernels wrote)."""
    t = wp.to_torch(array)
    return t[: batch_size * per].view(batch_size, per, *t.shape[1:])


def _problem_rows(rows, name: str, batch_size: int, batch: str = "") -> np.ndarray:
    """``rows`` as a 1-D int64 array of indices of a batch of ``batch_size`` problems (checked; ``batch``
    names that batch in the message)."""
    rows = np.asarray(rows)
    if rows.ndim != 1 or not (rows.size == 0 or np.issubdtype(rows.dtype, np.integer)):
        raise ValueError(f"{name} must be a 1-D integer array, got dtype {rows.dtype} shape {rows.shape}")
    if rows.size and (rows.min() < 0 or rows.max() >= batch_size):
        raise ValueError(f"{name} must lie in [0, {batch_size}){batch}, got {rows.min()}..{rows.max()}")
    return rows.astype(np.int64)


def _load_change(start: dict, end: dict) -> np.ndarray:
    """(B, K) change of every load and target along a load path, per problem (the predictor compares it)."""
    B = len(start["dof"])
    return np.concatenate(
        [(end[k] - start[k]).reshape(B, -1) for k in ("dof", "nodal_force", "prescribed", "pressure")]
        + [pose_change(start["poses"], end["poses"]).reshape(B, -1)],
        1,
    )


@dataclass
class _LoadPath:
    """Per-problem load stepping along a load path from ``start`` to ``end`` (dicts of (B, ...) loads, as
    ``QuasiStaticSolver._loads_now``): converged fraction, next trial fraction, failed attempts, counts."""

    start: dict
    end: dict
    change: np.ndarray  # (B, K) end - start (_load_change)
    todo: np.ndarray  # (B,) bool: on the path, not at its end and not flagged
    lam_done: np.ndarray  # (B,) load fraction of the last converged increment
    lam_try: np.ndarray  # (B,) load fraction of the increment being solved
    bisections: np.ndarray  # (B,) failed increments on this path
    runaways: np.ndarray  # (B,) failed increments on this path whose force-controlled travel ran away
    relag_every: np.ndarray  # (B,) bool: re-lag friction at every Newton iteration (after a failure)
    newton_total: np.ndarray  # (B,) Newton iterations on this path
    linear_total: np.ndarray  # (B,) Krylov iterations on this path
    residual: np.ndarray  # (B,) residual of the last Newton solve
    releasing: np.ndarray  # (B,) bool: Newton runs without the stabilization springs (stabilization_release)
    held_newton: np.ndarray  # (B,) iterations of the stabilized Newton solve before the release
    held_linear: np.ndarray
    relaxes: np.ndarray  # (B,) re-referenced stabilized solves of this increment (stabilization_relax)
    relaxing: np.ndarray  # (B,) bool: Newton runs such a solve
    spring_scale: np.ndarray  # (B,) fraction of the stabilization springs in its solves (relax decay)
    anchored: np.ndarray  # (B,) bool: its reference (friction anchor) moved; the increment's start is kept
    snapping: np.ndarray  # (B,) bool: the increment being solved is the force_maximum_snap attempt
    snap_tried: np.ndarray  # (B,) bool: this load step had its force_maximum_snap attempt

    @classmethod
    def between(cls, start: dict, end: dict) -> _LoadPath:
        """The path from ``start`` to ``end``, no problem on it yet (:meth:`begin`)."""
        B = len(start["dof"])
        return cls(
            start=start,
            end=end,
            change=_load_change(start, end),
            todo=np.zeros(B, dtype=bool),
            lam_done=np.zeros(B),
            lam_try=np.zeros(B),
            bisections=np.zeros(B, dtype=int),
            runaways=np.zeros(B, dtype=int),
            relag_every=np.zeros(B, dtype=bool),
            newton_total=np.zeros(B, dtype=int),
            linear_total=np.zeros(B, dtype=int),
            residual=np.zeros(B),
            releasing=np.zeros(B, dtype=bool),
            held_newton=np.zeros(B, dtype=int),
            held_linear=np.zeros(B, dtype=int),
            relaxes=np.zeros(B, dtype=int),
            relaxing=np.zeros(B, dtype=bool),
            spring_scale=np.ones(B),
            anchored=np.zeros(B, dtype=bool),
            snapping=np.zeros(B, dtype=bool),
            snap_tried=np.zeros(B, dtype=bool),
        )

    def begin(self, mask: np.ndarray, initial_fraction: float) -> None:
        """The masked problems start the path (``start``, ``end`` and ``change`` rows set by the caller)."""
        self.todo[mask] = True
        self.lam_done[mask] = 0.0
        self.lam_try[mask] = float(np.clip(initial_fraction, 1e-6, 1.0))
        counts = (self.bisections, self.runaways, self.newton_total, self.linear_total)
        for a in (*counts, self.held_newton, self.held_linear, self.relaxes):
            a[mask] = 0
        self.relag_every[mask] = False
        self.releasing[mask] = False
        self.relaxing[mask] = False
        self.snapping[mask] = False
        self.snap_tried[mask] = False
        self.spring_scale[mask] = 1.0
        self.anchored[mask] = False
        self.residual[mask] = 0.0


@dataclass
class _NewtonRun:
    """Per-problem state of the Newton iterations of the current load increments: a problem enters with
    ``QuasiStaticSolver._newton_begin`` and leaves ``working`` when it converges (``ok``) or fails."""

    relag_every: np.ndarray  # (B,) bool, shared with the load path
    working: np.ndarray  # (B,) bool: iterating
    started: np.ndarray  # (B,) bool: begun and not yet settled by the load stepping
    ok: np.ndarray
    status: np.ndarray  # (B,) SolveStatus of a failure
    passes: np.ndarray  # (B,) passes since the start (a safety bound)
    iters: np.ndarray  # (B,) Newton iterations
    lin_iters: np.ndarray  # (B,) Krylov iterations
    residual: np.ndarray  # (B,) last residual [N]
    tol: np.ndarray  # (B,) Newton tolerance at the last residual [N]
    relag: np.ndarray  # (B,) bool: re-lag the friction normal forces at the next pass
    relags: np.ndarray  # (B,) re-lags of converged but inconsistent states
    last_relag: np.ndarray  # (B,) iteration of the last such re-lag
    stale: np.ndarray  # (B,) bool: the next re-lag extrapolates (Aitken)
    exact: np.ndarray  # (B,) int32: exact Hessian
    damping: np.ndarray  # (B,) Levenberg-Marquardt factor of the exact Hessian
    stale_step: np.ndarray  # (B,) bool: chord Newton's last step came from a stale factor and was cut
    dof_targets: np.ndarray  # (B, D) |actuator force targets| (force scale of the tolerance)
    cap: np.ndarray  # (B,) Newton iterations of a solve (since its last re-lag) before the increment fails
    snap: np.ndarray  # (B,) bool: the increment is a force_maximum_snap attempt (cap: force_maximum_snap)
    max_step: float  # largest vertex or travel move per Newton step [m]
    escape: float  # object motion within one increment that flags ESCAPED [m]

    @classmethod
    def empty(cls, batch_size: int, num_dofs: int, relag_every, max_step, escape) -> _NewtonRun:
        B = batch_size
        return cls(
            max_step=max_step,
            escape=escape,
            relag_every=relag_every,
            working=np.zeros(B, dtype=bool),
            started=np.zeros(B, dtype=bool),
            ok=np.zeros(B, dtype=bool),
            status=np.full(B, SolveStatus.NOT_CONVERGED, dtype=np.int32),
            passes=np.zeros(B, dtype=int),
            iters=np.zeros(B, dtype=int),
            lin_iters=np.zeros(B, dtype=int),
            residual=np.full(B, np.inf),
            tol=np.zeros(B),
            relag=np.zeros(B, dtype=bool),
            relags=np.zeros(B, dtype=int),
            last_relag=np.zeros(B, dtype=int),
            stale=np.zeros(B, dtype=bool),
            exact=np.zeros(B, dtype=np.int32),
            damping=np.zeros(B),
            stale_step=np.zeros(B, dtype=bool),
            dof_targets=np.zeros((B, num_dofs)),
            cap=np.zeros(B, dtype=int),
            snap=np.zeros(B, dtype=bool),
        )


class QuasiStaticSolver:
    """Quasi-static FEM solver for B problems sharing one tet mesh and one set of rigid bodies.

    Args:
        mesh: the object's rest configuration.
        bodies: rigid bodies that may touch the object (planes, spheres, capsules, triangle meshes).
        material: one :class:`Material` or a list of B (the problems may differ in material).
        batch_size: number of independent problems B (different grasps, loads, materials).
        fixed: Dirichlet constraints: vertex indices (all components fixed) or an (N, 3) bool mask.
        device: Warp device ("cpu", "cuda", "cuda:0", ...); default: Warp's default device.
        options: :class:`SolverOptions`.
        pressure_surface: optional :class:`PressureSurface`, the triangles a gas presses on; its gas law
            per problem is given to :meth:`solve` (``pressure=``, default: no pressure).

    Per-problem settings: :meth:`set_material`, :meth:`set_body_pose`, :meth:`set_friction`; loads and
    targets are given to :meth:`solve` (they persist, so the next call continues from them).
    """

    def __init__(
        self,
        mesh: TetMesh,
        bodies=(),
        material: Material | list[Material] | None = None,
        batch_size: int = 1,
        fixed=None,
        device=None,
        options: SolverOptions | None = None,
        pressure_surface: PressureSurface | None = None,
    ):
        wp.init()
        if not isinstance(mesh, TetMesh):
            raise TypeError(f"mesh must be a TetMesh, got {type(mesh).__name__}")
        if int(batch_size) < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        self.mesh = mesh
        self.batch_size = B = int(batch_size)
        self.device = wp.get_device(device)
        self.options = options or SolverOptions()
        self.linear_solver = self.options.linear_solver

        if isinstance(bodies, (RigidBody, str)) or not isinstance(bodies, Iterable):
            raise TypeError(
                f"bodies must be a list of RigidBody instances, got {type(bodies).__name__}"
                + (" (wrap the one body in a list: [body])" if isinstance(bodies, RigidBody) else "")
            )
        self.bodies = list(bodies)
        for body in self.bodies:
            if not isinstance(body, RigidBody):
                raise TypeError(f"bodies must be RigidBody instances, got {type(body).__name__} {body!r}")
        names = [b.name for b in self.bodies]
        if len(set(names)) != len(names):
            raise BodyError(f"body names must be unique, got {names}")
        self.dof_names: list[str] = []
        self.dof_mode: list[str] = []
        body_dof = []
        for body in self.bodies:
            name = body.dof_name
            if name is None:
                body_dof.append(-1)
                continue
            if name not in self.dof_names:
                self.dof_names.append(name)
                self.dof_mode.append(body.control.mode)
            d = self.dof_names.index(name)
            if self.dof_mode[d] != body.control.mode:
                raise BodyError(f"bodies sharing dof {name!r} must use the same control mode")
            body_dof.append(d)
        self.num_bodies = K = len(self.bodies)
        self.num_dofs = D = len(self.dof_names)
        N = mesh.num_vertices
        self.rows_per_problem = R = N + D
        dev = self.device
        if self.linear_solver == "auto":
            dense = 3 * R <= DENSE_AUTO_MAX_UNKNOWNS["cuda" if dev.is_cuda else "cpu"]
            self.linear_solver = "dense" if dense else ("cg" if dev.is_cuda else "amg")
            if self.options.self_contact > 0 and not dense:
                self.linear_solver = "direct"  # the iterative solvers lack the self-contact couplings

        # ---------------- mesh data
        self._rest = wp.array(mesh.points, dtype=wp.vec3d, device=dev)
        self._tets = wp.array(mesh.tets.astype(np.int32), dtype=wp.int32, device=dev)
        self._rest_inverse = wp.array(mesh.rest_shape_inverse, dtype=wp.mat33d, device=dev)
        self._volume = wp.array(mesh.volumes, dtype=wp.float64, device=dev)
        self._vertex_weight = wp.array(mesh.vertex_tet_volume, dtype=wp.float64, device=dev)
        # one penalty length for the whole mesh (median surface edge): under a uniform pressure every vertex
        # then penetrates equally, so the penalty does not perturb the pressure distribution
        self.contact_length = mesh.median_surface_edge_length
        self._size = wp.array(np.full(N, self.contact_length), dtype=wp.float64, device=dev)
        self.num_surface = S = len(mesh.surface_vertices)

        # ---------------- Dirichlet constraints and free mask of every row
        fixed_mask = np.zeros((N, 3), dtype=bool)
        if fixed is not None:
            f = np.asarray(fixed)
            if f.dtype == bool:
                if f.shape != (N, 3):
                    raise ValueError(f"a boolean fixed mask must have shape ({N}, 3), got {f.shape}")
                fixed_mask = f.copy()
            else:
                idx = f.astype(np.int64).ravel()
                if idx.size and (idx.min() < 0 or idx.max() >= N):
                    raise ValueError(f"fixed vertex indices must be in [0, {N})")
                fixed_mask[idx] = True
        self.fixed_mask = fixed_mask
        free = np.zeros((R, 3))
        free[:N] = ~fixed_mask
        for d, mode in enumerate(self.dof_mode):
            free[N + d, 0] = 1.0 if mode == "force" else 0.0
        self._free = wp.array(free, dtype=wp.vec3d, device=dev)

        # ---------------- sparse system
        self._near_nullspace = rigid_body_modes(mesh.points, B, D)
        self.pattern = BlockPattern.build(mesh, D)
        self.system = BatchedSystem(self.pattern, B, dev, points=mesh.points)
        # chord Newton (SolverOptions.max_factor_reuse): per problem, the Newton steps taken with its stored
        # factorization and the Levenberg-Marquardt damping it was made with
        reuse = self.options.max_factor_reuse
        self._max_factor_reuse = int(MAX_FACTOR_REUSE_DEFAULT[dev.is_cuda] if reuse is None else reuse)
        self._reuse_factors = self._max_factor_reuse > 0 and self.linear_solver in FACTORIZING_SOLVERS
        trials = self.options.line_search_trials
        self._line_search_trials = T = int(
            LINE_SEARCH_TRIALS_DEFAULT[dev.is_cuda] if trials is None else trials
        )
        self.system.keep_factors = self._reuse_factors
        self.system.factor_streams = int(self.options.factor_streams)
        self.system.factor_graphs = float(self.options.factor_graphs)
        if self._reuse_factors and self.linear_solver in ("dense", "dense_banded") and dev.is_cuda:
            import torch

            _, total = torch.cuda.mem_get_info(wp.device_to_torch(dev))
            kept = B * (3 * R) ** 2 * 8
            if kept > DENSE_KEPT_FACTORS_MAX_MEMORY_FRACTION * total:
                raise ValueError(
                    f"dense factorizations kept for reuse need {kept / 1e9:.1f} GB ({B} problems of {3 * R} "
                    f"unknowns), over {DENSE_KEPT_FACTORS_MAX_MEMORY_FRACTION:.0%} of the device's "
                    f"{total / 1e9:.1f} GB: use SolverOptions(max_factor_reuse=0) or a smaller batch"
                )
        self._factor_steps = np.zeros(B, dtype=int)
        self._factor_damping = np.zeros(B)
        pad = lambda a: a if a.size else np.zeros((1, max(S, 1)), dtype=np.int32)  # noqa: E731
        self._blocks = ck.ContactBlocks()
        self._blocks.vertex_diag = wp.array(self.pattern.vertex_diag, dtype=wp.int32, device=dev)
        self._blocks.dof_diag = wp.array(
            self.pattern.dof_diag if D else np.zeros(1, np.int32), dtype=wp.int32, device=dev
        )
        self._blocks.dof_vertex = wp.array(pad(self.pattern.dof_vertex), dtype=wp.int32, device=dev)
        self._blocks.vertex_dof = wp.array(pad(self.pattern.vertex_dof), dtype=wp.int32, device=dev)
        self._blocks.blocks_per_problem = self.pattern.nnz
        self._blocks.rows_per_problem = R
        self._build_contact_points()
        P = self.num_contact_points
        self._tet_blocks = wp.array(self.pattern.tet_blocks, dtype=wp.int32, device=dev)
        #: self-contact of the object's surface (SolverOptions.self_contact > 0), else None
        model = self.options.self_contact_model
        self._self_contact = (
            SelfContact(
                mesh,
                self.pattern,
                B,
                self.contact_length,
                dev,
                model=model,
                friction=self.options.self_contact_friction,
            )
            if self.options.self_contact > 0
            else None
        )
        if self._self_contact is not None:
            # the factorizing solvers add the vertex-triangle couplings (the whole Gauss-Newton Hessian)
            self.system.coupling = self._self_contact.coupling

        # ---------------- rigid bodies
        self._body_dof = np.array(body_dof, dtype=np.int32)
        self._shape_frames = (
            np.stack([b.shape.shape_frame() for b in self.bodies]) if K else np.zeros((0, 4, 4))
        )
        self._axes_local = np.array([b.control.axis for b in self.bodies]).reshape(K, 3)
        self._poses = np.broadcast_to(np.eye(4), (B, K, 4, 4)).copy()
        self._friction = np.tile([b.friction for b in self.bodies], (B, 1)).reshape(B, K)
        self._warp_meshes = []
        mesh_points = [np.zeros((1, 3))]
        mesh_offset = np.zeros(K, dtype=np.int32)
        mesh_ids = np.zeros(K, dtype=np.uint64)
        offset = 1
        for k, body in enumerate(self.bodies):
            if isinstance(body.shape, TriangleMesh):
                wm = wp.Mesh(
                    points=wp.array(body.shape.vertices.astype(np.float32), dtype=wp.vec3, device=dev),
                    indices=wp.array(body.shape.faces.astype(np.int32).ravel(), dtype=wp.int32, device=dev),
                    support_winding_number=True,
                )
                self._warp_meshes.append(wm)
                mesh_ids[k] = wm.id
                mesh_offset[k] = offset
                mesh_points.append(body.shape.vertices)
                offset += len(body.shape.vertices)
        ba = ck.BodyArrays()
        ba.kind = wp.array(
            [SHAPE_KIND[type(b.shape)] for b in self.bodies] or [0], dtype=wp.int32, device=dev
        )
        #: (B, K) radius of each problem's spheres, capsules and rounded boxes [m] (set_body_radius)
        self._radius = np.tile([getattr(b.shape, "radius", 0.0) for b in self.bodies], (B, 1))
        ba.radius = wp.array(self._radius.reshape(-1) if K else [0.0], dtype=wp.float64, device=dev)
        ba.half_length = wp.array(
            [getattr(b.shape, "half_length", 0.0) for b in self.bodies] or [0.0], dtype=wp.float64, device=dev
        )
        ba.half_extents = wp.array(
            [getattr(b.shape, "inner_half_extents", np.ones(3)) for b in self.bodies] or [np.ones(3)],
            dtype=wp.vec3d,
            device=dev,
        )
        ba.mesh = wp.array(mesh_ids if K else np.zeros(1, np.uint64), dtype=wp.uint64, device=dev)
        ba.mesh_point_offset = wp.array(
            mesh_offset if K else np.zeros(1, np.int32), dtype=wp.int32, device=dev
        )
        ba.mesh_points = wp.array(np.concatenate(mesh_points), dtype=wp.vec3d, device=dev)
        ba.dof = wp.array(self._body_dof if K else np.zeros(1, np.int32), dtype=wp.int32, device=dev)
        nbk = max(B * K, 1)
        ba.rotation = wp.zeros(nbk, dtype=wp.mat33d, device=dev)
        ba.translation = wp.zeros(nbk, dtype=wp.vec3d, device=dev)
        ba.axis = wp.zeros(nbk, dtype=wp.vec3d, device=dev)
        ba.friction = wp.zeros(nbk, dtype=wp.float64, device=dev)
        ba.ref_rotation = wp.zeros(nbk, dtype=wp.mat33d, device=dev)
        ba.ref_translation = wp.zeros(nbk, dtype=wp.vec3d, device=dev)
        ba.num_bodies = K
        ba.query_distance = float(self.options.query_distance)
        self._bodies = ba

        # ---------------- gas pressure on a cavity (pressure.py)
        self.pressure_surface = pressure_surface
        if pressure_surface is not None:
            if not isinstance(pressure_surface, PressureSurface):
                raise TypeError(
                    f"pressure_surface must be a PressureSurface, got {type(pressure_surface).__name__}"
                )
            pf = pressure_surface.faces
            if pf.min() < 0 or pf.max() >= N:
                raise ValueError(f"pressure_surface face indices must lie in [0, {N})")
            pairs = [(pf[:, i], pf[:, j]) for i in range(3) for j in range(3)]
            blocks = [self.pattern.block_index(r, c) for r, c in pairs]
            if any(np.any(k < 0) for k in blocks):
                raise ValueError(
                    "pressure_surface faces must be triangles of the mesh (their edges tet edges)"
                )
            self._pressure_faces = wp.array(pf, dtype=wp.int32, device=dev)
            self._pressure_blocks = wp.array(np.stack(blocks, axis=1), dtype=wp.int32, device=dev)
            self._pressure_point = wp.vec3d(*pressure_surface.reference_point)
            self.rest_cavity_volume = pressure_surface.volume(mesh.points)
            if not self.rest_cavity_volume + pressure_surface.external_volume > 0:
                raise ValueError(
                    f"the pressurized cavity has rest volume {self.rest_cavity_volume:.4g} m^3 (plus "
                    f"external {pressure_surface.external_volume:.4g} m^3): faces must point into the gas"
                )
        self._gas_law = np.zeros((B, 2))  # per problem p0 [Pa], C [J]
        self._gas_pressure = wp.zeros(B, dtype=wp.float64, device=dev)
        self._gas_k = np.zeros(B)  # -dp/dV at the last assembly
        self._volume_gradient = wp.zeros(B * R, dtype=wp.vec3d, device=dev)
        self._volume_sum = wp.zeros(T * B, dtype=wp.float64, device=dev)  # per trial state (line search)

        # ---------------- per-problem state (q packs u and the travels, B * R rows)
        self._q = wp.zeros(B * R, dtype=wp.vec3d, device=dev)
        self._q_ref = wp.zeros_like(self._q)
        # the stabilization springs' reference: _q_ref itself, or (stabilization_relax) a copy of it that the
        # re-referenced stabilized solves of a failed release move
        relax = self.options.stabilization_release and self.options.stabilization_relax > 0
        self._q_spring = wp.zeros_like(self._q) if relax else self._q_ref
        self._q_start = wp.zeros_like(self._q) if relax else None  # an anchored increment's start
        self._stick_start: dict[int, np.ndarray] = {}  # and its stick stretches, per problem
        # line-search trial states: T per problem, trial-major (state t B + b is trial t of problem b)
        self._q_trial = wp.zeros(T * B * R, dtype=wp.vec3d, device=dev)
        self._trial_step = wp.zeros(T * B, dtype=wp.float64, device=dev)
        self._last_increment = wp.zeros_like(self._q)  # q change of each problem's last converged increment
        self._last_change = np.zeros((B, 0))  # and the load change that caused it (predictor)
        self._load_steps = np.zeros(B, dtype=int)  # load steps each problem finished since its rest state
        self._positions = wp.zeros(B * N, dtype=wp.vec3d, device=dev)
        self._positions_ref = wp.zeros_like(self._positions)
        self._positions_trial = wp.zeros(T * B * N, dtype=wp.vec3d, device=dev)
        self._travel = wp.zeros(max(B * D, 1), dtype=wp.float64, device=dev)
        self._travel_ref = wp.zeros_like(self._travel)
        self._travel_trial = wp.zeros(max(T * B * D, 1), dtype=wp.float64, device=dev)
        nc = max(B * P * K, 1)
        self._lag_force = wp.zeros(nc, dtype=wp.float64, device=dev)
        self._lag_normal = wp.zeros(nc, dtype=wp.vec3d, device=dev)
        # Aitken relaxation of stale re-lags (see _relag_friction): last lag residual and factor per problem
        self._relag_residual = wp.zeros(nc, dtype=wp.float64, device=dev)
        self._relag_relaxation = wp.zeros(B, dtype=wp.float64, device=dev)  # w of this re-lag, per problem
        self._relag_omega = np.ones(self.batch_size)
        self._relag_has_residual = np.zeros(self.batch_size, dtype=bool)
        self._stick_stretch = wp.zeros(nc, dtype=wp.vec3d, device=dev)
        self._exact_hessian = wp.zeros(B, dtype=wp.int32, device=dev)  # per problem: 1 = exact Hessian
        self._c_force = wp.zeros(nc, dtype=wp.float64, device=dev)
        self._c_normal = wp.zeros(nc, dtype=wp.vec3d, device=dev)
        self._c_gap = wp.zeros(nc, dtype=wp.float64, device=dev)
        self._c_friction = wp.zeros(nc, dtype=wp.vec3d, device=dev)
        self._c_stick = wp.zeros(nc, dtype=wp.int32, device=dev)
        self._nodal_force = wp.zeros(B * N, dtype=wp.vec3d, device=dev)
        self._dof_force = wp.zeros(max(B * D, 1), dtype=wp.float64, device=dev)
        self._energy = wp.zeros(T * B, dtype=wp.float64, device=dev)  # per trial state
        self._drift = wp.zeros(B, dtype=wp.float64, device=dev)  # largest vertex move in an increment
        self._step_stats = wp.zeros((3, B), dtype=wp.float64, device=dev)  # slope, largest vertex / dof step
        self._newton_scales = wp.zeros((3, B), dtype=wp.float64, device=dev)  # force, load scale; residual
        self._friction_stats = wp.zeros((3, B), dtype=wp.float64, device=dev)  # lag errors, Aitken dots
        self._step = wp.zeros(B, dtype=wp.float64, device=dev)
        self._stabilization_force = wp.zeros(B, dtype=wp.float64, device=dev)

        # current loads and targets (host), and sticky status
        self._masses = mesh.vertex_masses(1.0)  # per unit density, scaled by each problem's density
        self._load = BodyLoad()
        self._dof_target = np.zeros((B, D))
        self._prescribed = np.zeros((B, N, 3))
        self._gas_target = np.zeros((B, 2))  # requested gas law (p0, C) per problem
        self.status = np.zeros(B, dtype=np.int32)
        self.set_material(material if material is not None else Material(1e6))
        self._update_bodies()
        self.reset()

    def _build_contact_points(self) -> None:
        """The contact points (``SolverOptions.contact_subdivisions``, :func:`contact.surface_contact_points`)
        on the device, with the BSR blocks of their vertex pairs and their vertices' surface indices."""
        mesh, dev = self.mesh, self.device
        vertex, weight, area = ck.surface_contact_points(mesh, self.options.contact_subdivisions)
        #: (P, 3) mesh vertices, (P, 3) barycentric weights and (P,) areas of the contact points; the first
        #: S are the surface vertices (the only ones with contact_subdivisions = 1)
        self.contact_point_vertices, self.contact_point_weights = vertex, weight
        self.num_contact_points = P = len(vertex)
        pairs = np.arange(9)
        blocks = self.pattern.block_index(vertex[:, pairs // 3].ravel(), vertex[:, pairs % 3].ravel())
        if np.any(blocks < 0):  # surface triangles are tet faces: their edges are in the pattern
            raise ValueError("contact points must lie on triangles of the mesh (their edges tet edges)")
        points = ck.ContactPoints()
        points.vertex = wp.array(vertex, dtype=wp.vec3i, device=dev)
        points.weight = wp.array(weight, dtype=wp.vec3d, device=dev)
        surface_index = np.searchsorted(mesh.surface_vertices, vertex).astype(np.int32)
        points.surface = wp.array(surface_index, dtype=wp.vec3i, device=dev)
        points.area = wp.array(area, dtype=wp.float64, device=dev)
        points.size = wp.array(np.full(P, self.contact_length), dtype=wp.float64, device=dev)
        points.blocks = wp.array(blocks.reshape(P, 9), dtype=wp.int32, device=dev)
        self._points = points
        #: (P,) surface index of each point's vertices (for lumping point forces onto surface vertices)
        self._point_surface = surface_index

    # ------------------------------------------------------------------ per-problem settings
    def set_material(self, material, rows=None) -> None:
        """One :class:`Material` for all problems, or a sequence of B.

        ``rows``: only these problems (integer indices; ``material`` one Material or one per row) take the
        new material, with their increment stabilization springs on and their factorizations dropped; the
        other problems keep their materials, spring states, damping and factorizations (a problem of a
        :meth:`solve_stream` may take a job of another material while the others iterate)."""
        if rows is None:
            rows = np.arange(self.batch_size)
            whole = True
        else:
            rows = _problem_rows(rows, "rows", self.batch_size)
            whole = False
        what = f"{self.batch_size}" if whole else f"{len(rows)} (one per row)"
        if isinstance(material, Material):
            mats = [material] * len(rows)
        elif isinstance(material, Iterable) and not isinstance(material, str):
            mats = list(material)
        else:
            raise TypeError(
                f"material must be a Material or a list of {what} Materials, got {type(material).__name__} "
                f"{material!r} (e.g. fem.Material(youngs_modulus, poisson_ratio, density))"
            )
        if len(mats) != len(rows) or not all(isinstance(m, Material) for m in mats):
            raise ValueError(f"material must be a Material or a list of {what} Materials")
        if whole:
            self.materials = mats
        else:
            self.materials = list(self.materials)
            for r, m in zip(rows.tolist(), mats):
                self.materials[r] = m
        all_mats = self.materials
        dev = self.device
        B, N, D = self.batch_size, self.mesh.num_vertices, self.num_dofs
        self._youngs_np = np.array([m.youngs_modulus for m in all_mats])
        self._density_np = np.array([m.density for m in all_mats])
        self._youngs = wp.array(self._youngs_np, dtype=wp.float64, device=dev)
        self._mu = wp.array([m.shear_modulus for m in all_mats], dtype=wp.float64, device=dev)
        self._lam = wp.array([m.lame_lambda for m in all_mats], dtype=wp.float64, device=dev)
        self._model = wp.array([MATERIAL_MODELS.index(m.model) for m in all_mats], dtype=wp.int32, device=dev)
        self._barrier = any(m.model == "neohookean" for m in all_mats)
        #: absolute Newton residual floor per problem [N] (1e-14 E h^2)
        self._newton_atol = 1e-14 * self._youngs_np * self.mesh.diameter**2
        E = self._youngs_np[rows]
        scale = self.options.regularization * E[:, None] * self.mesh.vertex_size[None, :]
        stab = self.options.stabilization * E[:, None] * self.mesh.vertex_size[None, :]
        shift = np.zeros((len(rows), self.rows_per_problem, 3))
        shift[:, :N, :] = (scale + stab)[:, :, None]
        if D:
            shift[:, N:, 0] = self.options.regularization * E[:, None] * self.mesh.diameter
        damping = np.zeros_like(shift)  # Levenberg-Marquardt unit per row: E h [N/m]
        damping[:, :N, :] = (E[:, None] * self.mesh.vertex_size[None])[..., None]
        if whole:
            self._regularization_np = scale
            self._stabilization_np = stab  # (B, N) spring constants [N/m], for _stabilize()
            self._diag_shift_base = shift
            self._damping_scale = damping
            self._shift_damping = np.zeros(B)  # the damping that _diag_shift holds, per problem
            self._stabilization = wp.array(stab.reshape(-1), dtype=wp.float64, device=dev)
            self._diag_shift = wp.array(shift.reshape(-1, 3), dtype=wp.vec3d, device=dev)
            self.system.forget_factors()  # factorizations of the old materials' Hessians
            return
        self._regularization_np[rows] = scale
        self._stabilization_np[rows] = stab
        self._diag_shift_base[rows] = shift
        self._damping_scale[rows] = damping
        self._shift_damping[rows] = 0.0
        self._put_rows(self._stabilization, N, rows, stab)
        self._put_rows(self._diag_shift, self.rows_per_problem, rows, shift)
        mask = np.zeros(B, dtype=bool)
        mask[rows] = True
        self.system.forget_factors(mask)

    def _dof(self, name: str) -> int:
        if name not in self.dof_names:
            raise KeyError(f"unknown dof {name!r}; dofs are {self.dof_names}")
        return self.dof_names.index(name)

    def _body(self, name: str) -> int:
        for k, b in enumerate(self.bodies):
            if b.name == name:
                return k
        raise KeyError(f"no rigid body named {name!r}; bodies are {[b.name for b in self.bodies]}")

    def set_body_pose(self, name: str, pose, rows=None) -> None:
        """Pose (4x4, or one per problem) of body ``name``'s frame in the object frame at travel 0.

        Changing a pose moves the body instantly (no friction history is carried across the change); to
        drag contacts along (shear, twist), move the body with ``solve(body_poses=...)`` instead.
        ``rows``: only these problems (integer indices; ``pose`` 4x4 or one per row) move; the others keep
        their poses, friction history and factorizations.
        """
        k = self._body(name)
        T = check_rigid_transform(pose, f"pose of body {name!r}")
        if rows is None:
            self._poses[:, k] = np.broadcast_to(T, (self.batch_size, 4, 4))
            self._update_bodies(reference=True)
            self._stick_stretch.zero_()
            self.system.forget_factors()
            return
        rows = _problem_rows(rows, "rows", self.batch_size)
        self._poses[rows, k] = np.broadcast_to(T, (len(rows), 4, 4))
        mask = np.zeros(self.batch_size, dtype=bool)
        mask[rows] = True
        self._update_bodies()
        self._commit_body_reference(mask)
        self._put_rows(self._stick_stretch, self.num_contact_points * self.num_bodies, rows)  # zeroed
        self.system.forget_factors(mask)

    def set_body_radius(self, name: str, radius, rows=None) -> None:
        """Radius [m] of sphere or capsule body ``name``, per problem: a scalar, or one per problem (one per
        row with ``rows``). Like :meth:`set_body_pose`, the body changes at once: the changed problems lose
        that body's friction history and their factorizations; the others are untouched. (A body's radius
        as built is its shape's; each problem may have its own, e.g. a data set's indenters of several
        sizes streamed through one batch.)"""
        k = self._body(name)
        shape = self.bodies[k].shape
        if not isinstance(shape, (Sphere, Capsule)):
            raise ValueError(
                f"only sphere and capsule radii can be set, body {name!r} is a {type(shape).__name__}"
            )
        rows = np.arange(self.batch_size) if rows is None else _problem_rows(rows, "rows", self.batch_size)
        r = np.asarray(radius, dtype=np.float64)
        r = np.broadcast_to(r, (len(rows),)) if r.ndim == 0 else r.ravel()
        if r.shape != (len(rows),) or not np.all(np.isfinite(r)) or np.any(r <= 0):
            raise ValueError(
                f"radius of body {name!r} must be {len(rows)} finite values > 0 m, got {radius!r}"
            )
        changed = rows[self._radius[rows, k] != r]
        if not changed.size:
            return
        self._radius[rows, k] = r
        self._bodies.radius.assign(wp.array(self._radius.reshape(-1), dtype=wp.float64, device=self.device))
        mask = np.zeros(self.batch_size, dtype=bool)
        mask[changed] = True
        stretch = self._host_rows(self._stick_stretch, self.num_contact_points * self.num_bodies, changed)
        stretch = stretch.reshape(len(changed), self.num_contact_points, self.num_bodies, 3)
        stretch[:, :, k] = 0.0
        self._put_rows(self._stick_stretch, self.num_contact_points * self.num_bodies, changed, stretch)
        self.system.forget_factors(mask)

    def _put_rows(self, array: wp.array, per: int, rows: np.ndarray, values=0.0) -> None:
        """Write ``values`` ((len(rows), per, ...), or a scalar: zero by default) into the ``per`` entries of
        each problem of ``rows`` of a problem-major device array."""
        if per == 0 or not len(rows):
            return
        import torch

        wp.synchronize_device(self.device)
        view = _problem_view(array, self.batch_size, per)
        index = torch.as_tensor(np.asarray(rows, dtype=np.int64), device=view.device)
        if np.ndim(values):
            values = torch.as_tensor(np.asarray(values), dtype=view.dtype, device=view.device)
            values = values.reshape(len(rows), *view.shape[1:])
        view[index] = values
        if self.device.is_cuda:
            torch.cuda.synchronize(view.device)

    def _host_rows(self, array: wp.array, per: int, rows: np.ndarray) -> np.ndarray:
        """The ``per`` entries of each problem of ``rows`` of a problem-major device array, on the host
        ((len(rows), per, ...); gathered on the device first, so only those problems are copied)."""
        import torch

        wp.synchronize_device(self.device)
        view = _problem_view(array, self.batch_size, per)
        index = torch.as_tensor(np.asarray(rows, dtype=np.int64), device=view.device)
        return view.index_select(0, index).cpu().numpy()

    def set_friction(self, name: str, mu) -> None:
        """Coulomb coefficient of body ``name`` with the object (scalar or (B,))."""
        k = self._body(name)
        mu = _per_problem(mu, self.batch_size, f"friction of body {name!r}")
        if np.any(mu < 0):
            raise ValueError("friction coefficients must be >= 0")
        self._friction[:, k] = mu
        self._update_bodies()

    def _world_frames(self):
        """Per (b, k): rotation, origin at travel 0, and control axis, all in the object frame."""
        W = self._poses @ self._shape_frames[None]
        axes = np.einsum("bkij,kj->bki", self._poses[..., :3, :3], self._axes_local)
        return W[..., :3, :3], W[..., :3, 3], axes

    def _update_bodies(self, reference: bool = False):
        if not self.num_bodies:
            return
        rot, origin, axes = self._world_frames()
        dev = self.device
        ba = self._bodies
        ba.rotation.assign(wp.array(rot.reshape(-1, 3, 3), dtype=wp.mat33d, device=dev))
        ba.translation.assign(wp.array(origin.reshape(-1, 3), dtype=wp.vec3d, device=dev))
        ba.axis.assign(wp.array(axes.reshape(-1, 3), dtype=wp.vec3d, device=dev))
        ba.friction.assign(wp.array(self._friction.reshape(-1), dtype=wp.float64, device=dev))
        if reference:
            self._commit_body_reference(np.ones(self.batch_size, dtype=bool))

    def _commit_body_reference(self, mask: np.ndarray):
        """Store each masked problem's current body placements (with travel) as the friction reference."""
        if not self.num_bodies:
            return
        rot, origin, axes = self._world_frames()
        travel = self._travel.numpy()[: self.batch_size * self.num_dofs].reshape(
            self.batch_size, self.num_dofs
        )
        t_body = np.zeros((self.batch_size, self.num_bodies))
        for k, d in enumerate(self._body_dof):
            if d >= 0:
                t_body[:, k] = travel[:, d]
        placed = origin + t_body[..., None] * axes
        ref_rot = self._bodies.ref_rotation.numpy().reshape(self.batch_size, self.num_bodies, 3, 3)
        ref_pos = self._bodies.ref_translation.numpy().reshape(self.batch_size, self.num_bodies, 3)
        ref_rot[mask] = rot[mask]
        ref_pos[mask] = placed[mask]
        self._bodies.ref_rotation.assign(
            wp.array(ref_rot.reshape(-1, 3, 3), dtype=wp.mat33d, device=self.device)
        )
        self._bodies.ref_translation.assign(
            wp.array(ref_pos.reshape(-1, 3), dtype=wp.vec3d, device=self.device)
        )

    def reset(self) -> None:
        """Back to the rest state: zero displacement and travel, no loads, statuses cleared."""
        self._q.zero_()
        self._q_ref.zero_()
        self._q_spring.zero_()
        self._last_increment.zero_()
        self._last_change = np.zeros((self.batch_size, 0))
        self._load_steps[:] = 0
        self._lag_force.zero_()
        self._stick_stretch.zero_()
        self._load = BodyLoad()
        self._dof_target[:] = 0.0
        self._prescribed[:] = 0.0
        self._gas_law[:] = 0.0
        self._gas_target[:] = 0.0
        self.status[:] = SolveStatus.CONVERGED
        #: (B,) load steps since the reset reached past a force maximum by a snap (force_maximum_snap)
        self.snaps = np.zeros(self.batch_size, dtype=int)
        # (B,) bool: a snap attempt was made; every later increment gets its Newton iterations and budget
        self._snapping = np.zeros(self.batch_size, dtype=bool)
        #: Newton passes of the batch since the reset (one assembly each, for every problem then iterating)
        self.newton_passes = 0
        self._stabilization_at_convergence = np.zeros(self.batch_size)
        self.system.forget_factors()
        self._unpack(self._q, self._positions, self._travel)
        self._unpack(self._q_ref, self._positions_ref, self._travel_ref)
        self._commit_body_reference(np.ones(self.batch_size, dtype=bool))

    def copy_state_from(self, other: QuasiStaticSolver, rows, into=None) -> None:
        """Problem ``into[i]`` of this solver takes the complete state of problem ``rows[i]`` of ``other``.

        ``other`` must be built on the same mesh (points and tets), the same rigid bodies (names, shapes,
        controls, dofs), Dirichlet constraints, pressure surface, options and device (it may be this
        solver); ``rows`` is an integer array into ``other``'s problems (repeats allowed: one solved problem
        copied to several replicas) and ``into`` the distinct problems of this solver that take them
        (default: all, ``rows`` then names one source per problem). Copied: displacements and travels
        (current, converged reference, trial and predictor), friction lags, stick stretches and their Aitken
        relaxation, body poses, radii and frictions with their friction reference placements, materials, body
        loads, dof targets, prescribed displacements, nodal and dof forces, gas laws and pressures, statuses,
        Levenberg-Marquardt and chord-Newton bookkeeping, and the stored factorizations (shared: they are
        never modified after being made, only dropped or replaced). The other problems of this solver keep
        their states (and factorizations, unless a copied material differs from the one it replaces: then
        every problem refactors). The solver is batch-independent, so the next solve of a copied problem is
        bit-identical to the one its source problem would make.
        """
        if not isinstance(other, QuasiStaticSolver):
            raise TypeError(f"other must be a QuasiStaticSolver, got {type(other).__name__}")
        B, Bo = self.batch_size, other.batch_size
        rows = _problem_rows(rows, "rows", Bo, " (other's batch)")
        if into is None:
            if len(rows) != B:
                raise ValueError(
                    f"rows must name one problem of other per problem of this solver: {B}, got {len(rows)}"
                )
            into = np.arange(B)
        else:
            into = _problem_rows(into, "into", B, " (this batch)")
            if len(into) != len(rows):
                raise ValueError(f"into names {len(into)} problems for {len(rows)} rows")
            if len(np.unique(into)) != len(into):
                raise ValueError("into must name distinct problems")
        self._check_compatible(other)
        if not rows.size:
            return
        N, D, K, P, R = (
            self.mesh.num_vertices,
            self.num_dofs,
            self.num_bodies,
            self.num_contact_points,
            self.rows_per_problem,
        )
        import torch

        dev = torch.device(wp.device_to_torch(self.device))
        src_rows = torch.as_tensor(rows, device=dev)
        dst_rows = torch.as_tensor(into, device=dev)

        def gather(dst, src, per: int):
            """dst (this batch's array) rows ``into`` <- src (other's) problem rows, ``per`` entries each."""
            if per == 0:
                return
            _problem_view(dst, B, per)[dst_rows] = _problem_view(src, Bo, per)[src_rows]

        # materials first (set_material rebuilds the copied problems' material rows and drops their
        # factorizations; the copies below then give them their sources' springs, shifts and factors)
        changed = [
            (i, other.materials[r])
            for i, r in zip(into.tolist(), rows.tolist())
            if self.materials[i] is not other.materials[r] and self.materials[i] != other.materials[r]
        ]
        if changed:
            self.set_material([m for _, m in changed], rows=[i for i, _ in changed])
        wp.synchronize_device(self.device)
        if self.device.is_cuda:
            torch.cuda.synchronize(dev)
        per_row = [
            "_q",
            "_q_ref",
            "_q_trial",
            "_last_increment",
            "_volume_gradient",
            "_diag_shift",
        ]
        if self._q_spring is not self._q_ref:
            per_row.append("_q_spring")
        for name in per_row:
            gather(getattr(self, name), getattr(other, name), R)
        for name in ("_positions", "_positions_ref", "_positions_trial", "_nodal_force", "_stabilization"):
            gather(getattr(self, name), getattr(other, name), N)
        for name in ("_travel", "_travel_ref", "_travel_trial", "_dof_force"):
            gather(getattr(self, name), getattr(other, name), D)
        contacts = (
            "_lag_force",
            "_lag_normal",
            "_relag_residual",
            "_stick_stretch",
            "_c_force",
            "_c_normal",
            "_c_gap",
            "_c_friction",
            "_c_stick",
        )
        for name in contacts:
            gather(getattr(self, name), getattr(other, name), P * K)
        per_problem = (
            "_relag_relaxation",
            "_exact_hessian",
            "_energy",
            "_step",
            "_stabilization_force",
            "_gas_pressure",
            "_volume_sum",
        )
        for name in per_problem:
            gather(getattr(self, name), getattr(other, name), 1)
        for name in (
            "rotation",
            "translation",
            "axis",
            "friction",
            "ref_rotation",
            "ref_translation",
            "radius",
        ):
            gather(getattr(self._bodies, name), getattr(other._bodies, name), K)
        sysm, src = self.system, other.system
        for name in ("gradient", "rhs", "increment"):
            gather(getattr(sysm, name), getattr(src, name), R)
        gather(sysm.values, src.values, self.pattern.nnz)
        if self.device.is_cuda:
            torch.cuda.synchronize(dev)
        # host state
        self._poses[into] = other._poses[rows]
        self._friction[into] = other._friction[rows]
        self._radius[into] = other._radius[rows]
        self._relag_omega[into] = other._relag_omega[rows]
        self._relag_has_residual[into] = other._relag_has_residual[rows]
        if self._last_change.shape[1:] != other._last_change.shape[1:]:  # (B, 0): no change committed yet
            self._last_change = np.zeros((B, *other._last_change.shape[1:]))
        self._last_change[into] = other._last_change[rows]
        self._load_steps[into] = other._load_steps[rows]
        self._factor_steps[into] = other._factor_steps[rows]
        self._diag_shift_base[into] = other._diag_shift_base[rows]  # with the source's spring state
        self._shift_damping[into] = other._shift_damping[rows]
        self._factor_damping[into] = other._factor_damping[rows]
        self._gas_law[into] = other._gas_law[rows]
        self._gas_k = np.broadcast_to(np.asarray(self._gas_k, dtype=np.float64), (B,)).copy()
        self._gas_k[into] = np.asarray(other._gas_k)[rows]
        self._gas_target[into] = other._gas_target[rows]
        self._dof_target[into] = other._dof_target[rows]
        self._prescribed[into] = other._prescribed[rows]
        self.status[into] = other.status[rows]
        self.snaps[into] = other.snaps[rows]
        self._snapping[into] = other._snapping[rows]
        self._stabilization_at_convergence[into] = other._stabilization_at_convergence[rows]
        mine, theirs = self._load.arrays(B), other._load.arrays(Bo)
        for k in mine:
            mine[k] = np.array(mine[k])
            mine[k][into] = theirs[k][rows]
        self._load = BodyLoad(**mine)
        # linear-solver state: factorizations (shared, read-only once made), multigrid hierarchies
        sysm.share_factors_from(src, rows, into)

    def _check_compatible(self, other: QuasiStaticSolver) -> None:
        """Raise ValueError unless ``other`` has this solver's mesh, bodies, constraints, options, device."""

        def fail(what: str, mine, theirs):
            raise ValueError(
                f"cannot copy solver state: different {what} (this solver {mine}, other {theirs})"
            )

        m, o = self.mesh, other.mesh
        if (m.num_vertices, m.num_tets) != (o.num_vertices, o.num_tets):
            fail("mesh sizes (vertices, tets)", (m.num_vertices, m.num_tets), (o.num_vertices, o.num_tets))
        if m is not o and not (np.array_equal(m.points, o.points) and np.array_equal(m.tets, o.tets)):
            fail("mesh", "points/tets", "other points/tets")
        mine = [(b.name, type(b.shape).__name__, b.dof_name, b.control.mode) for b in self.bodies]
        theirs = [(b.name, type(b.shape).__name__, b.dof_name, b.control.mode) for b in other.bodies]
        if mine != theirs:
            fail("bodies (name, shape, dof, control)", mine, theirs)
        geometry = ("kind", "half_length", "half_extents", "mesh_points")  # radii are per problem: state
        built = [[getattr(b.shape, "radius", 0.0) for b in s.bodies] for s in (self, other)]
        if not (
            built[0] == built[1]
            and np.array_equal(self._shape_frames, other._shape_frames)
            and np.array_equal(self._axes_local, other._axes_local)
            and all(
                np.array_equal(getattr(self._bodies, g).numpy(), getattr(other._bodies, g).numpy())
                for g in geometry
            )
        ):
            fail("body geometry", [b.name for b in self.bodies], [b.name for b in other.bodies])
        if not np.array_equal(self.fixed_mask, other.fixed_mask):
            fail("fixed (Dirichlet) masks", int(self.fixed_mask.sum()), int(other.fixed_mask.sum()))
        if self.options != other.options or self.linear_solver != other.linear_solver:
            fail("options", self.options, other.options)
        if self.device != other.device:
            fail("devices", self.device, other.device)
        ps, po = self.pressure_surface, other.pressure_surface
        if (ps is None) != (po is None) or (
            ps is not None
            and not (
                np.array_equal(ps.faces, po.faces)
                and np.array_equal(ps.reference_point, po.reference_point)
                and ps.external_volume == po.external_volume
            )
        ):
            fail("pressure surfaces", ps, po)

    # ------------------------------------------------------------------ kernels plumbing
    def _unpack(self, q, positions, travel, states: int | None = None):
        """positions and travel of the first ``states`` packed states of q (default: one per problem)."""
        wp.launch(
            kk.unpack_state_kernel,
            dim=(self.batch_size if states is None else states, self.rows_per_problem),
            inputs=[q, self._rest, self.mesh.num_vertices, self.num_dofs, positions, travel],
            device=self.device,
        )

    def _active_array(self, mask: np.ndarray):
        return wp.array(mask.astype(np.int32), dtype=wp.int32, device=self.device)

    def _energy_at(self, q, positions, travel, active) -> np.ndarray:
        """Pi per problem at state q (whose unpacked positions/travel are given)."""
        return self._energies_at(q, positions, travel, active, 1)[0]

    def _energies_at(self, q, positions, travel, active, trials: int) -> np.ndarray:
        """(trials, B) Pi of ``trials`` packed states per problem, trial-major (state t B + b is trial t of
        problem b; see ``trial_state_kernel``), in one set of launches; inactive problems' entries are 0."""
        B, N, D = self.batch_size, self.mesh.num_vertices, self.num_dofs
        TB = trials * B
        e = self._energy
        e.zero_()
        wp.launch(
            ek.elastic_energy_kernel,
            dim=(TB, self.mesh.num_tets),
            inputs=[
                positions,
                self._tets,
                self._rest_inverse,
                self._volume,
                self._mu,
                self._lam,
                self._model,
                N,
                active,
                e,
            ],
            device=self.device,
        )
        if self.num_bodies:
            wp.launch(
                ck.contact_energy_kernel,
                dim=(TB, self.num_contact_points, self.num_bodies),
                inputs=[
                    *self._contact_inputs(positions, travel),
                    active,
                    e,
                ],
                device=self.device,
            )
        if self._self_contact is not None:
            self._self_contact.add_energy(positions, TB, self._youngs, *self._self_contact_law(), active, e)
        wp.launch(
            kk.external_work_kernel,
            dim=(TB, self.rows_per_problem),
            inputs=[q, self._nodal_force, self._dof_force, N, D, active, e],
            device=self.device,
        )
        if self.options.stabilization > 0:
            wp.launch(
                kk.stabilization_energy_kernel,
                dim=(TB, N),
                inputs=[q, self._q_spring, self._stabilization, N, self.rows_per_problem, active, e],
                device=self.device,
            )
        energy = e.numpy()[:TB].reshape(trials, B).copy()
        if self.pressure_surface is not None:
            dv = self._cavity_volume_change(positions, TB).reshape(trials, B)
            work = pk.gas_work(
                self._gas_law, dv, self.rest_cavity_volume, self.pressure_surface.external_volume
            )
            energy -= np.where(active.numpy() != 0, work, 0.0)
        return energy

    def _cavity_volume_change(self, positions, states: int | None = None) -> np.ndarray:
        """V - V0 [m^3] of the pressurized cavity at the given positions: (B,), or (states,) for that many
        packed states (line-search trials)."""
        states = self.batch_size if states is None else states
        dv = self._volume_sum
        dv.zero_()
        wp.launch(
            pk.cavity_volume_change_kernel,
            dim=(states, len(self.pressure_surface.faces)),
            inputs=[
                positions,
                self._rest,
                self._pressure_faces,
                self._pressure_point,
                self.mesh.num_vertices,
                dv,
            ],
            device=self.device,
        )
        return dv.numpy()[:states].copy()

    def _assemble_pressure(self, active, load_scale):
        """Gas pressure at the current state: gradient -p dV/dx, sparse Hessian -p d2V/dx2, and the
        rank-one coefficient -dp/dV (``self._gas_k``, applied in the linear solve)."""
        B, N = self.batch_size, self.mesh.num_vertices
        vh = self.pressure_surface.external_volume
        vol = self.rest_cavity_volume + self._cavity_volume_change(self._positions)
        p = pk.gas_pressure(self._gas_law, vol, vh)
        self._gas_pressure.assign(p)
        self._gas_k = np.where(active.numpy() != 0, pk.gas_stiffness(self._gas_law, vol, vh), 0.0)
        F = len(self.pressure_surface.faces)
        self._volume_gradient.zero_()
        wp.launch(
            pk.volume_gradient_kernel,
            dim=(B, F),
            inputs=[self._positions, self._pressure_faces, N, self.rows_per_problem, self._volume_gradient],
            device=self.device,
        )
        wp.launch(
            pk.pressure_gradient_kernel,
            dim=(B, N),
            inputs=[
                self._volume_gradient,
                self._gas_pressure,
                self.rows_per_problem,
                active,
                self.system.gradient,
                load_scale,
            ],
            device=self.device,
        )
        wp.launch(
            pk.pressure_hessian_kernel,
            dim=(B, F),
            inputs=[
                self._positions,
                self._pressure_faces,
                self._pressure_point,
                self._gas_pressure,
                self._pressure_blocks,
                N,
                self.pattern.nnz,
                active,
                self.system.values,
            ],
            device=self.device,
        )
        return vol, p

    def _gas_direction(self, k: np.ndarray):
        """(B, 3R) torch tensor on the device: u = dV/dx on the free components of the problems with a gas
        stiffness ``k`` > 0 (zero rows elsewhere), after the assembly that computed dV/dx."""
        import torch

        B, R = self.batch_size, self.rows_per_problem
        dev = torch.device(wp.device_to_torch(self.device))
        wp.synchronize_device(self.device)
        grad = wp.to_torch(self._volume_gradient)[: B * R].reshape(B, R, 3)
        free = wp.to_torch(self._free).reshape(1, R, 3)
        stiff = torch.as_tensor(k > 0, device=dev).reshape(B, 1, 1)
        return torch.where(stiff, grad * free, 0.0).reshape(B, R * 3)

    def _gas_rank_one(self, k: np.ndarray, u, rtol: float) -> int:
        """Add the gas stiffness k u u^T (``u`` = dV/dx on free components, :meth:`_gas_direction`; ``k`` =
        -dp/dV per problem, 0 where not iterating) to the Newton step by Sherman-Morrison: with H0 x0 = r
        (already in ``increment``) and H0 y = u,

            x = x0 - y k (u . x0) / (1 + k u . y).

        y comes with the step where the factorizing solvers solved u as a second column
        (``BatchedSystem.extra_rhs``, set by :meth:`_newton_pass`), else from a second solve of the same
        matrices. On the device throughout. Returns the Krylov iterations of the second solve."""
        import torch

        B, n = self.batch_size, 3 * self.rows_per_problem
        sysm = self.system
        dev = torch.device(wp.device_to_torch(self.device))
        increment = wp.to_torch(sysm.increment)[: B * n // 3].reshape(B, n)
        x0, y, n_lin = increment, sysm.extra_increment, 0
        if y is None:
            x0 = increment.clone()
            rhs = wp.to_torch(sysm.rhs)[: B * n // 3].reshape(B, n)
            r0 = rhs.clone()
            rhs.copy_(u)
            if dev.type == "cuda":
                torch.cuda.synchronize(dev)
            n_lin, _ = self._linear_solve(rtol)
            wp.synchronize_device(self.device)
            y = increment.clone()
            rhs.copy_(r0)
        kt = torch.as_tensor(k, device=dev)
        ux = torch.einsum("bi,bi->b", u, x0)
        uy = torch.einsum("bi,bi->b", u, y)
        coef = torch.where(kt > 0, kt * ux / (1.0 + kt * uy), 0.0)
        increment.copy_(x0 - coef[:, None] * y)
        sysm.extra_increment = None
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)
        return n_lin

    def _assemble(self, active) -> None:
        """Gradient and Hessian at the current state; the elastic force scale and the load scale per problem
        into rows 0 and 1 of ``self._newton_scales`` (read back with the residual, one synchronization)."""
        B, N, D = self.batch_size, self.mesh.num_vertices, self.num_dofs
        sysm = self.system
        sysm.zero()
        self._newton_scales.zero_()
        fscale, lscale = self._newton_scales[0], self._newton_scales[1]
        wp.launch(
            ek.elastic_gradient_hessian_kernel,
            dim=(B, self.mesh.num_tets),
            inputs=[
                self._positions,
                self._tets,
                self._rest_inverse,
                self._volume,
                self._mu,
                self._lam,
                self._model,
                self._tet_blocks,
                N,
                self.rows_per_problem,
                self.pattern.nnz,
                active,
                self._exact_hessian,
                sysm.gradient,
                fscale,
                sysm.values,
            ],
            device=self.device,
        )
        if self.num_bodies:
            wp.launch(
                ck.contact_gradient_hessian_kernel,
                dim=(B, self.num_contact_points, self.num_bodies),
                inputs=[
                    *self._contact_inputs(self._positions, self._travel),
                    self._blocks,
                    active,
                    self._exact_hessian,
                    sysm.gradient,
                    sysm.values,
                ],
                device=self.device,
            )
        if self._self_contact is not None:
            # the pairs of this state, kept for the line search that follows (one energy per iteration)
            self._self_contact.update_pairs(self._positions)
            self._self_contact.add_gradient_hessian(
                self._positions,
                self._youngs,
                *self._self_contact_law(),
                self.rows_per_problem,
                self.pattern.nnz,
                active,
                self._free,
                sysm.gradient,
                sysm.values,
            )
        wp.launch(
            kk.external_gradient_kernel,
            dim=(B, self.rows_per_problem),
            inputs=[self._nodal_force, self._dof_force, N, D, active, sysm.gradient, lscale],
            device=self.device,
        )
        if self.options.stabilization > 0:
            self._stabilization_force.zero_()
            wp.launch(
                kk.stabilization_gradient_kernel,
                dim=(B, N),
                inputs=[
                    self._q,
                    self._q_spring,
                    self._stabilization,
                    N,
                    self.rows_per_problem,
                    active,
                    sysm.gradient,
                    self._stabilization_force,
                ],
                device=self.device,
            )
        if self.pressure_surface is not None:
            self._assemble_pressure(active, lscale)
        sysm.constrain(self._free, self._diag_shift)

    def _contact_inputs(self, positions, travel) -> list:
        """The leading arguments shared by every contact kernel (see ``contact.py``)."""
        return [
            positions,
            self._positions_ref,
            travel,
            self._points,
            self._youngs,
            float(self.options.contact_stiffness),
            float(self.options.contact_smoothing),
            float(self.options.friction_stick_slip),
            self._bodies,
            self._lag_force,
            self._lag_normal,
            self._stick_stretch,
            self.mesh.num_vertices,
            self.num_dofs,
        ]

    def _self_contact_law(self) -> tuple[float, float]:
        """kappa (``SolverOptions.self_contact`` times the rigid one) and zeta of the self-contact penalty."""
        o = self.options
        return float(o.contact_stiffness) * float(o.self_contact), float(o.contact_smoothing)

    def self_contact_forces(self) -> tuple[np.ndarray, np.ndarray]:
        """At the current state of every problem: (B, N, 3) self-contact force on each vertex [N] (they sum
        to zero per problem) and (B, S) penetration of each surface vertex (``mesh.surface_vertices`` order)
        behind the triangle it is paired with [m], 0 where it is not behind one. Needs
        ``SolverOptions.self_contact`` > 0."""
        if self._self_contact is None:
            raise ValueError("self_contact_forces needs SolverOptions.self_contact > 0")
        self._unpack(self._q, self._positions, self._travel)
        return self._self_contact.forces(self._positions, self._youngs, *self._self_contact_law())

    def _contact_state(self, positions, travel):
        if not self.num_bodies:
            return
        wp.launch(
            ck.contact_state_kernel,
            dim=(self.batch_size, self.num_contact_points, self.num_bodies),
            inputs=[
                *self._contact_inputs(positions, travel),
                self._c_force,
                self._c_normal,
                self._c_gap,
                self._c_friction,
                self._c_stick,
            ],
            device=self.device,
        )

    def _pinched(self, mask: np.ndarray) -> np.ndarray:
        """(B,) problems in ``mask`` whose current state has a pinched vertex (:func:`pinched_vertices`)."""
        B, S, K = self.batch_size, self.num_contact_points, self.num_bodies
        if K < 2 or not mask.any():
            return np.zeros(B, dtype=bool)
        self._unpack(self._q, self._positions, self._travel)
        self._contact_state(self._positions, self._travel)
        m = np.nonzero(mask)[0]
        fn = self._host_rows(self._c_force, S * K, m).reshape(len(m), S, K)
        nrm = self._host_rows(self._c_normal, S * K, m).reshape(len(m), S, K, 3)
        out = np.zeros(B, dtype=bool)
        out[m] = pinched_vertices(fn, nrm).any(axis=1)
        return out

    def _friction_inconsistent(self, mask: np.ndarray, tol: np.ndarray) -> np.ndarray:
        """Problems in ``mask`` whose friction capacities, computed from lagged normal forces, are not
        consistent with their current normal forces: some contact's capacity error ``mu (|N - N_lag| +
        N |n - n_lag|)`` exceeds ``tol`` and the summed error exceeds ``friction_rtol sum mu N``. Reduced per
        problem on the device: only three numbers per problem come back. With self-contact friction its
        friction pairs are checked the same way (their lagged normal forces against the barrier's now)."""
        stale = np.zeros(self.batch_size, dtype=bool)
        sc = self._self_contact
        stats = self._friction_stats
        if sc is not None and sc.friction > 0 and mask.any():
            sc.update_pairs(self._positions)
            stats.zero_()
            sc.friction_lag_error(
                self._positions, self._youngs, self._self_contact_law()[0], self._active_array(mask), stats
            )
            largest, total, capacity = stats.numpy()
            stale |= mask & (largest > tol) & (total > self.options.friction_rtol * capacity)
        if not self.num_bodies or not np.any(self._friction[mask] > 0):
            return stale
        self._contact_state(self._positions, self._travel)
        stats.zero_()
        largest, total, capacity = stats[0], stats[1], stats[2]
        wp.launch(
            ck.friction_lag_error_kernel,
            dim=(self.batch_size, self.num_contact_points * self.num_bodies),
            inputs=[
                self._c_force,
                self._c_normal,
                self._lag_force,
                self._lag_normal,
                self._bodies.friction,
                self.num_bodies,
                self.num_contact_points * self.num_bodies,
                self._active_array(mask),
                largest,
                total,
                capacity,
            ],
            device=self.device,
        )
        largest, total, capacity = stats.numpy()
        return stale | (mask & (largest > tol) & (total > self.options.friction_rtol * capacity))

    def _relag_friction(self, mask: np.ndarray, accelerate: np.ndarray | None = None):
        """Lagged normal forces and normals <- current ones, for the problems in ``mask``.

        For the problems in ``accelerate`` (re-lags of a converged but stale state) the normal forces are
        extrapolated instead: the lag fixed point ``N_lag = N(x(N_lag))`` is iterated with Aitken's dynamic
        relaxation (Irons & Tuck 1969; Kuttler & Wall 2008), ``N_lag <- N_lag + w_k r_k`` with the lag
        residual ``r_k = N - N_lag`` and ``w_k = -w_{k-1} r_{k-1}.(r_k - r_{k-1}) / |r_k - r_{k-1}|^2``
        (clipped to [0.5, 4], 1 at the first re-lag of an increment), then clamped at N >= 0. The plain
        re-lag (w = 1) contracts only about 2x per re-lag on tilted grasps, where friction carries the
        load; the relaxation extrapolates that geometric sequence towards its limit. Runs on the device;
        only the two dot products per accelerated problem come back to the host.
        """
        sc = self._self_contact
        if sc is not None and sc.friction > 0 and mask.any():
            # the self-contact's friction pairs and normal forces from this iterate (slips from the
            # increment's start, as the rigid contact's stick anchors)
            sc.update_pairs(self._positions)
            sc.lag_friction(
                self._positions, self._youngs, self._self_contact_law()[0], self._active_array(mask), False
            )
        if not self.num_bodies or not np.any(self._friction[mask] > 0):
            return
        self._contact_state(self._positions, self._travel)
        slots = self.num_contact_points * self.num_bodies
        acc = mask & (accelerate if accelerate is not None else False)
        if acc.any():
            prev = acc & self._relag_has_residual
            if prev.any():
                stats = self._friction_stats
                stats.zero_()
                num, den = stats[0], stats[1]
                wp.launch(
                    ck.friction_lag_residual_dots_kernel,
                    dim=(self.batch_size, slots),
                    inputs=[
                        self._c_force,
                        self._lag_force,
                        self._relag_residual,
                        slots,
                        self._active_array(prev),
                        num,
                        den,
                    ],
                    device=self.device,
                )
                num, den = stats.numpy()[:2, prev]
                with np.errstate(divide="ignore", invalid="ignore"):
                    w = np.where(den > 0, -self._relag_omega[prev] * num / den, 1.0)
                self._relag_omega[prev] = np.clip(np.nan_to_num(w, nan=1.0), 0.5, 4.0)
            self._relag_omega[acc & ~self._relag_has_residual] = 1.0
            self._relag_has_residual[acc] = True
        self._relag_relaxation.assign(np.where(acc, self._relag_omega, 1.0))
        wp.launch(
            ck.friction_relag_kernel,
            dim=(self.batch_size, slots),
            inputs=[
                self._c_force,
                self._c_normal,
                self._lag_force,
                self._lag_normal,
                self._relag_residual,
                slots,
                self._active_array(mask),
                self._active_array(acc),
                self._relag_relaxation,
            ],
            device=self.device,
        )

    # ------------------------------------------------------------------ loads at a load fraction
    def _apply_increment(self, lam: np.ndarray, start: dict, end: dict, mask: np.ndarray):
        """Set loads, actuator targets and prescribed displacements of the masked problems to
        start + lam (end - start), and move their prescribed components there (only their rows are
        computed: without a barrier the load stepping starts a few problems' increments at a time)."""
        B, N, D = self.batch_size, self.mesh.num_vertices, self.num_dofs
        m = np.nonzero(mask)[0]
        lam_m = lam[m]
        w = lam_m[:, None, None]
        # (only the masked problems' rows travel to the device)
        nf = start["nodal_force"][m] + w * (end["nodal_force"][m] - start["nodal_force"][m])
        self._put_rows(self._nodal_force, N, m, nf)
        targets = start["dof"][m] + lam_m[:, None] * (end["dof"][m] - start["dof"][m])
        force_dofs = np.array([mode == "force" for mode in self.dof_mode], dtype=bool)
        moved = bool(D and not force_dofs.all()) or bool(self.fixed_mask.any())
        q = self._q.numpy().reshape(B, self.rows_per_problem, 3) if moved else None
        if D:
            dof_force = self._dof_force.numpy()[: B * D].reshape(B, D)
            dof_force[m] = np.where(force_dofs[None], targets, 0.0)
            self._dof_force.assign(np.concatenate([dof_force.ravel(), np.zeros(max(B * D, 1) - B * D)]))
            disp = np.nonzero(~force_dofs)[0]
            if disp.size:
                q[np.ix_(m, N + disp, [0])] = targets[:, disp][..., None]
        self._gas_law[m] = start["pressure"][m] + lam_m[:, None] * (end["pressure"][m] - start["pressure"][m])
        if self.num_bodies and end["poses"] is not start["poses"]:
            self._poses[m] = interpolate_poses(start["poses"][m], end["poses"][m], lam_m)
            self._update_bodies()
        if self.fixed_mask.any():
            pres = start["prescribed"][m] + w * (end["prescribed"][m] - start["prescribed"][m])
            qv = q[m, :N]
            qv[:, self.fixed_mask] = pres[:, self.fixed_mask]
            q[m, :N] = qv
        if moved:
            self._q.assign(q.reshape(-1, 3))
        self._unpack(self._q, self._positions, self._travel)

    def _loads_now(self) -> dict:
        masses = self._masses[None, :] * self._density_np[:, None]
        f = self._load.nodal_forces(self.mesh.points, masses, self.batch_size)
        return {
            "nodal_force": f,
            "dof": self._dof_target.copy(),
            "prescribed": self._prescribed.copy(),
            "pressure": self._gas_target.copy(),
            "poses": self._poses.copy(),
        }

    # ------------------------------------------------------------------ public solve
    def solve(
        self,
        targets: dict | None = None,
        body_load: BodyLoad | None = None,
        prescribed_displacement=None,
        initial_fraction: float = 1.0,
        pressure: PressureLoad | None = None,
        body_poses: dict | None = None,
    ) -> Equilibrium:
        """Move every problem from its current loads to the given ones and return the equilibria.

        Args:
            targets: dof name -> force [N] (force-controlled) or travel [m] (displacement-controlled),
                scalar or (B,). Unnamed dofs keep their current targets.
            body_load: new :class:`BodyLoad` (default: keep the current one).
            prescribed_displacement: (N, 3) or (B, N, 3) displacement of the fixed components [m].
            initial_fraction: first trial increment as a fraction of the whole change (the solver halves
                failing increments and grows successful ones on its own).
            pressure: new :class:`PressureLoad` of the pressure surface (default: keep the current one;
                between load increments the gas law's p0 and C are interpolated linearly).
            body_poses: body name -> new pose (4x4 or (B, 4, 4), as :meth:`set_body_pose`). Unlike
                ``set_body_pose``, the body travels there along the load path (translation linear, rotation
                along the geodesic, both with the load fraction) and drags its contacts with it: a sticking
                contact is carried along, a slipping one is held back by Coulomb friction (shear, twist). A
                problem that fails stays at the pose of its last converged increment.
        """
        B, N = self.batch_size, self.mesh.num_vertices
        start = self._loads_now()
        if targets:
            for name, value in targets.items():
                self._dof_target[:, self._dof(name)] = _per_problem(value, B, f"target {name!r}")
        if body_load is not None:
            if not isinstance(body_load, BodyLoad):
                raise TypeError("body_load must be a BodyLoad")
            body_load.arrays(B)  # validates shapes
            self._load = body_load
        if prescribed_displacement is not None:
            p = np.broadcast_to(np.asarray(prescribed_displacement, dtype=np.float64), (B, N, 3))
            if not np.all(np.isfinite(p)):
                raise ValueError("prescribed_displacement must be finite")
            self._prescribed = np.array(p)
        if pressure is not None:
            if not isinstance(pressure, PressureLoad):
                raise TypeError(f"pressure must be a PressureLoad, got {type(pressure).__name__}")
            if self.pressure_surface is None:
                raise ValueError("a pressure load needs a solver built with a pressure_surface")
            self._gas_target = pressure.arrays(B)
        end = self._loads_now()
        end["poses"] = start["poses"]
        if body_poses:
            end["poses"] = start["poses"].copy()
            for name, pose in body_poses.items():
                T = check_rigid_transform(pose, f"pose of body {name!r}")
                end["poses"][:, self._body(name)] = np.broadcast_to(T, (B, 4, 4))

        path = _LoadPath.between(start, end)
        path.begin(self.status == SolveStatus.CONVERGED, initial_fraction)
        self._advance(path, barrier=True)
        # problems that failed stay at their last converged state; record how far they got
        if end["poses"] is not start["poses"]:
            self._poses = interpolate_poses(start["poses"], end["poses"], path.lam_done)
            self._update_bodies()
        self._unpack(self._q, self._positions, self._travel)
        return self._results(path.lam_done, path.newton_total, path.linear_total, path.residual)

    def solve_sequence(
        self,
        levels,
        on_level: Callable[[int, Equilibrium], None] | None = None,
        progress: bool = False,
        check: Callable[[np.ndarray, Equilibrium, np.ndarray], np.ndarray] | None = None,
    ) -> list[Equilibrium]:
        """Solve a sequence of target levels; each problem starts its next level as soon as it has reached
        the current one (no barrier between the levels).

        The equilibria are those of ``[self.solve(targets=level) for level in levels]``, problem by problem
        (a problem's path depends only on its own data; with the solvers that factor one problem at a time
        they are bit-identical), but a batch no longer waits at every level for its slowest problem: while a
        hard grasp spends hundreds of Newton iterations on one force step, the others go on with theirs, and
        the batch takes about as many Newton iterations as its slowest problem's own path instead of the
        sum over the levels of each level's slowest problem. (:meth:`solve_stream` with one job per problem.)

        Args:
            levels: sequence of dicts dof name -> target (force [N] or travel [m], scalar or (B,)), as
                ``solve(targets=...)``; unnamed dofs keep their previous level's targets.
            on_level: ``on_level(k, equilibrium)`` is called for level k once every problem has reached it
                (or was flagged), in level order; it must not change the solver.
            progress: a progress bar over the levels all problems have reached.
            check: ``check(levels, part, rows)`` is called with the problems ``rows`` that have just reached
                the levels ``levels`` (one per row) and their equilibria ``part`` (one per row), before they
                go on; it returns one :class:`SolveStatus` code per row: ``CONVERGED`` lets the problem go on,
                any other code flags it there (as setting ``solver.status`` between two ``solve`` calls
                does), e.g. a tactile indenter that lost contact with the membrane.

        Returns the equilibria of the levels, one per level.
        """
        B = self.batch_size
        levels = list(levels)
        if not levels:
            raise ValueError("solve_sequence needs at least one level")
        table = []  # (B, D) dof targets of each level
        targets = self._dof_target.copy()
        for k, level in enumerate(levels):
            if not isinstance(level, Mapping):
                raise TypeError(f"level {k} must be a dict dof name -> target, got {type(level).__name__}")
            targets = targets.copy()
            for name, value in level.items():
                targets[:, self._dof(name)] = _per_problem(value, B, f"target {name!r} of level {k}")
            table.append(targets)
        table = np.stack(table)
        L = len(table)
        bar = None
        if progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=L, desc="load levels", leave=False)
        results: list[Equilibrium | None] = [None] * L
        filled = np.zeros((L, B), dtype=bool)
        emitted = 0

        def reached(problems: np.ndarray, steps: np.ndarray, part: Equilibrium) -> None:
            nonlocal emitted
            for k in np.unique(steps):
                sel = np.nonzero(steps == k)[0]
                if results[k] is None:
                    results[k] = part.take(np.zeros(B, dtype=int))
                results[k].put(problems[sel], part.take(sel))
                filled[k, problems[sel]] = True
            while emitted < L and filled[emitted].all():
                if on_level is not None:
                    on_level(emitted, results[emitted])
                emitted += 1
                if bar is not None:
                    bar.update(1)

        try:
            self._stream(
                B,
                lambda jobs, problems: [(table[:, j], None, None) for j in jobs],
                None,
                reached,
                None if check is None else (lambda jobs, steps, part: check(steps, part, jobs)),
            )
        finally:
            if bar is not None:
                bar.close()
        self._dof_target[:] = table[-1]  # flagged problems too, as after one solve() per level
        if emitted < L:  # cannot happen: every problem either reaches the last level or is flagged
            raise RuntimeError(f"solve_sequence ended with levels {emitted}..{L - 1} incomplete")
        return results

    def solve_stream(
        self,
        jobs,
        start: Callable[[np.ndarray, np.ndarray], None],
        on_levels: Callable[[np.ndarray, np.ndarray, Equilibrium], None],
        check: Callable[[np.ndarray, np.ndarray, Equilibrium], np.ndarray] | None = None,
        progress: bool = False,
    ) -> None:
        """Solve a queue of jobs, each a sequence of target levels, keeping the batch full: a problem that
        has finished its job (or was flagged) takes the next job of the queue at the next Newton pass.

        :meth:`solve_sequence` spares the batch the wait at every level for its slowest problem; the batch
        still ends with its slowest problem, and from there on the launches and synchronizations of every
        pass serve a few problems. Here the batch's B problems are slots: the work of many more jobs than B
        (a data set's indentation paths, squeeze ramps) flows through them, and the slow jobs' tails overlap
        with the others' work. Each job's equilibria are those :meth:`solve_sequence` gives it from the same
        start state (bit for bit with the solvers that factor one problem at a time).

        Args:
            jobs: a sequence of jobs; job j is a sequence of dicts dof name -> scalar target (force [N] or
                travel [m]), its levels; unnamed dofs keep their previous level's targets (the first
                level's: those of the problem after ``start``). A level may also move bodies: the key
                ``"body_poses"`` maps body names to 4x4 poses, reached as ``solve(body_poses=...)``
                reaches them (along the geodesic with the load fraction, dragging the contacts: shear,
                twist); unnamed bodies keep their previous level's poses (the first level's: the
                problem's after ``start``). The key ``"body_load"`` gives the level's :class:`BodyLoad`
                (fields of shape (3,): this job's gravity, frame accelerations), reached as
                ``solve(body_load=...)`` reaches it (its nodal forces linear in the load fraction); a
                level without it keeps the previous level's load (the first level's: the problem's after
                ``start``).
            start: ``start(problems, job_ids)`` must put the problems (integer indices) into the start states
                of the jobs, e.g. :meth:`copy_state_from` a solved template problem (``into=problems``) and
                :meth:`set_body_pose` (``rows=problems``); it must not touch the other problems. Called
                with the first min(B, J) jobs, then whenever problems have finished theirs. A problem whose
                ``status`` is not ``CONVERGED`` after it reports its job flagged at every level.
            on_levels: ``on_levels(job_ids, levels, part)`` with (job, level) pairs just reached and their
                equilibria (row i of ``part`` for pair i). Every level of every job is reported once and a
                job's levels in order; a job flagged at a level (no equilibrium, or by ``check``) reports it
                there with its status, and every later level with its last converged state and no load
                fraction, iterations or residual (as :meth:`solve` reports a flagged problem).
            check: ``check(job_ids, levels, part) -> codes`` for (job, level) pairs just reached: one
                :class:`SolveStatus` per row; any code but ``CONVERGED`` flags the job there.
            progress: a progress bar over the jobs.
        """
        jobs = list(jobs)
        moving = False  # some level moves a body: the load paths interpolate poses
        for j, job in enumerate(jobs):
            if isinstance(job, Mapping) or not len(job):
                raise ValueError(f"job {j} must be a non-empty sequence of levels (dicts dof name -> target)")
            for k, level in enumerate(job):
                if not isinstance(level, Mapping):
                    raise TypeError(f"level {k} of job {j} must be a dict dof name -> target")
                for name, value in level.items():
                    if name == "body_poses":
                        where = f"level {k} of job {j}"
                        if not isinstance(value, Mapping):
                            raise TypeError(f"body_poses of {where} must be a dict body name -> 4x4 pose")
                        for body, pose in value.items():
                            self._body(body)
                            if np.shape(pose) != (4, 4):
                                raise ValueError(
                                    f"pose of body {body!r} in {where} must be 4x4, got {np.shape(pose)}"
                                )
                            check_rigid_transform(pose, f"pose of body {body!r} in {where}")
                        moving = moving or bool(value)
                        continue
                    if name == "body_load":
                        if not isinstance(value, BodyLoad):
                            got = type(value).__name__
                            raise TypeError(
                                f"body_load of level {k} of job {j} must be a BodyLoad, got {got}"
                            )
                        value.arrays(1)  # one problem's load: every field (3,) or (1, 3)
                        continue
                    self._dof(name)
                    if not (np.ndim(value) == 0 and np.isfinite(value)):
                        raise ValueError(f"target {name!r} of level {k} of job {j} must be a finite scalar")

        def tables(job_ids, problems):
            """Each job's (L, D) dof targets, (L, K, 4, 4) body poses (None: no level moves a body) and
            per level its BodyLoad (None: no level sets one)."""
            out = []
            for j, b in zip(job_ids, problems):
                targets, rows = self._dof_target[b].copy(), []
                poses, pose_rows = self._poses[b].copy(), []
                load, loads = None, []
                for level in jobs[j]:
                    targets = targets.copy()
                    for name, value in level.items():
                        if name not in ("body_poses", "body_load"):
                            targets[self._dof(name)] = float(value)
                    if level.get("body_poses"):
                        poses = poses.copy()
                        for body, pose in level["body_poses"].items():
                            poses[self._body(body)] = pose
                    load = level.get("body_load", load)
                    rows.append(targets)
                    pose_rows.append(poses)
                    loads.append(load)
                moved = any(level.get("body_poses") for level in jobs[j])
                loaded = any("body_load" in level for level in jobs[j])
                out.append(
                    (np.stack(rows), np.stack(pose_rows) if moved else None, loads if loaded else None)
                )
            return out

        bar = None
        if progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=len(jobs), desc="jobs", leave=False)

        def reached(job_ids, steps, part):
            on_levels(job_ids, steps, part)
            if bar is not None:
                last = np.array([len(jobs[j]) - 1 for j in job_ids], dtype=int)
                bar.update(int((steps == last).sum()))

        try:
            self._stream(len(jobs), tables, start, reached, check, moving)
        finally:
            if bar is not None:
                bar.close()

    def _set_body_loads(self, rows: np.ndarray, loads) -> np.ndarray:
        """Problems ``rows`` take the body loads ``loads`` (one :class:`BodyLoad` each, fields (3,)), as
        ``solve(body_load=...)`` sets them; returns their (len(rows), N, 3) nodal forces [N]."""
        fields = {k: np.array(v) for k, v in self._load.arrays(self.batch_size).items()}
        for b, load in zip(rows.tolist(), loads):
            for k, v in load.arrays(1).items():
                fields[k][b] = v[0]
        self._load = BodyLoad(**fields)
        masses = self._masses[None, :] * self._density_np[rows][:, None]
        mine = BodyLoad(**{k: v[rows] for k, v in fields.items()})
        return mine.nodal_forces(self.mesh.points, masses, len(rows))

    def _stream(self, num_jobs: int, tables, start, reached, check, moving: bool = False) -> None:
        """The engine of :meth:`solve_sequence` and :meth:`solve_stream`: jobs 0..num_jobs-1 flow through
        the batch's problems. ``tables(job_ids, problems)`` gives each job's (L_j, D) dof targets, its
        (L_j, K, 4, 4) body poses (None: the job moves no body) and its L_j body loads (None: the job sets
        none; an entry None: the load the problem has) once its problem has been started
        (``start(problems, job_ids)``, or the problem as it is if ``start`` is None); ``reached(job_ids,
        levels, part)`` and ``check`` as solve_stream's ``on_levels`` and ``check``; ``moving``: some job
        moves a body (the load paths then interpolate the poses, as ``solve(body_poses=...)``)."""
        B = self.batch_size
        if start is None and num_jobs > B:
            raise ValueError(f"{num_jobs} jobs need a start function to share {B} problems")
        now = self._loads_now()
        end = {k: (v.copy() if k != "poses" or moving else v) for k, v in now.items()}
        path = _LoadPath.between(now, end)
        job_of = np.full(B, -1)  # the job each problem is working on (-1: none)
        level = np.zeros(B, dtype=int)
        table: dict[int, np.ndarray] = {}
        pose_table: dict[int, np.ndarray] = {}  # the jobs that move bodies: their poses per level
        load_table: dict[int, list] = {}  # the jobs that set body loads: their BodyLoad per level
        queue = [0]  # the next job to start

        def level_loads(rows: np.ndarray) -> None:
            """The body loads of ``rows``' current levels: the path's end nodal forces and the solver's
            body loads (as solve(body_load=...) sets them) of the problems whose job sets one."""
            sel = [
                b
                for b in rows.tolist()
                if int(job_of[b]) in load_table and load_table[int(job_of[b])][level[b]] is not None
            ]
            if sel:
                loads = [load_table[int(job_of[b])][level[b]] for b in sel]
                path.end["nodal_force"][sel] = self._set_body_loads(np.array(sel), loads)

        def settle_poses(rows: np.ndarray) -> None:
            """Bodies of ``rows`` at the poses of their last converged load fraction (as solve() leaves a
            problem that failed); a converged level's end pose is set as its last increment set it."""
            if moving and rows.size:
                self._poses[rows] = interpolate_poses(
                    path.start["poses"][rows], path.end["poses"][rows], path.lam_done[rows]
                )
                self._update_bodies()

        def report_flagged(part: Equilibrium, problems: np.ndarray, first: np.ndarray) -> None:
            """Jobs of flagged ``problems`` report the levels from ``first`` on at their last state."""
            for a in (part.load_fraction, part.newton_iterations, part.linear_iterations, part.residual):
                a[:] = 0
            ids, steps, rows = [], [], []
            for i, b in enumerate(problems):
                j = int(job_of[b])
                for k in range(int(first[i]), len(table[j])):
                    ids.append(j)
                    steps.append(k)
                    rows.append(i)
            if rows:
                reached(np.array(ids), np.array(steps), part.take(np.array(rows)))

        def finish(problems: np.ndarray) -> None:
            for b in problems:
                table.pop(int(job_of[b]), None)
                pose_table.pop(int(job_of[b]), None)
                load_table.pop(int(job_of[b]), None)
            job_of[problems] = -1

        def assign(free: np.ndarray) -> np.ndarray:
            """Start the next jobs on the ``free`` problems; returns the mask of those started."""
            started = np.zeros(B, dtype=bool)
            while free.size and queue[0] < num_jobs:
                n = min(free.size, num_jobs - queue[0])
                problems, free = free[:n], free[n:]
                ids = np.arange(queue[0], queue[0] + n)
                queue[0] += n
                if start is not None:
                    start(problems, ids)
                for j, (t, poses, loads) in zip(ids, tables(ids, problems)):
                    table[int(j)] = t
                    if poses is not None:
                        pose_table[int(j)] = poses
                    if loads is not None:
                        load_table[int(j)] = loads
                job_of[problems] = ids
                level[problems] = 0
                now = self._loads_now()
                for key in ("dof", "nodal_force", "prescribed", "pressure", "poses"):
                    path.start[key][problems] = now[key][problems]
                    path.end[key][problems] = now[key][problems]
                path.end["dof"][problems] = np.stack([table[int(j)][0] for j in ids])
                for b, j in zip(problems.tolist(), ids.tolist()):
                    if j in pose_table:
                        path.end["poses"][b] = pose_table[j][0]
                level_loads(problems)
                self._dof_target[problems] = path.end["dof"][problems]
                path.change[problems] = _load_change(
                    {k: v[problems] for k, v in path.start.items()},
                    {k: v[problems] for k, v in path.end.items()},
                )
                idle = problems[self.status[problems] != SolveStatus.CONVERGED]
                if idle.size:  # flagged before its job began: every level reports it at its state
                    part = self._results(np.zeros(B), np.zeros(B, int), np.zeros(B, int), np.zeros(B), idle)
                    report_flagged(part, idle, np.zeros(idle.size, dtype=int))
                    finish(idle)
                    free = np.concatenate([free, idle])
                started[problems] = self.status[problems] == SolveStatus.CONVERGED
            path.begin(started, 1.0)
            return started

        def level_done(left: np.ndarray) -> np.ndarray:
            """Report the problems that left their level; the converged ones move on (or take new jobs)."""
            rows = np.nonzero(left)[0]
            settle_poses(rows)
            part = self._results(path.lam_done, path.newton_total, path.linear_total, path.residual, rows)
            ids, steps = job_of[rows], level[rows]
            if check is not None:
                ok = np.nonzero(part.converged)[0]
                if ok.size:
                    codes = np.asarray(check(ids[ok], steps[ok], part.take(ok)))
                    if codes.shape != ok.shape:
                        raise ValueError(f"check must return {ok.size} status codes, got {codes.shape}")
                    flag = ok[codes != SolveStatus.CONVERGED]
                    part.status[flag] = codes[codes != SolveStatus.CONVERGED]
                    self.status[rows[flag]] = part.status[flag]
            reached(ids, steps, part)
            flagged = np.nonzero(self.status[rows] != SolveStatus.CONVERGED)[0]
            if flagged.size:
                report_flagged(part.take(flagged), rows[flagged], steps[flagged] + 1)
            last = np.array([len(table[int(j)]) - 1 for j in ids], dtype=int)
            going = (self.status[rows] == SolveStatus.CONVERGED) & (steps < last)
            move = np.zeros(B, dtype=bool)
            move[rows[going]] = True
            if move.any():
                level[move] += 1
                for key in ("dof", "nodal_force", "prescribed", "pressure"):
                    path.start[key][move] = path.end[key][move]
                path.end["dof"][move] = np.stack(
                    [table[int(job_of[b])][level[b]] for b in np.nonzero(move)[0]]
                )
                level_loads(np.nonzero(move)[0])
                if moving:  # the next level starts at the poses this one reached
                    path.start["poses"][move] = self._poses[move]
                    for b in np.nonzero(move)[0]:
                        poses = pose_table.get(int(job_of[b]))
                        if poses is not None:
                            path.end["poses"][b] = poses[level[b]]
                self._dof_target[move] = path.end["dof"][move]
                path.change[move] = _load_change(
                    {k: v[move] for k, v in path.start.items()}, {k: v[move] for k, v in path.end.items()}
                )
                path.begin(move, 1.0)
            done = rows[~going]
            finish(done)
            return move | assign(done)

        assign(np.arange(B))
        self._advance(path, barrier=False, level_done=level_done)
        self._unpack(self._q, self._positions, self._travel)

    def ramp(
        self,
        steps: int,
        targets: dict | None = None,
        body_load: BodyLoad | None = None,
        progress: bool = False,
        pressure: PressureLoad | None = None,
    ) -> list[Equilibrium]:
        """Solve at ``steps`` evenly spaced load levels from the current loads to the given ones (the gas
        law's p0 and C in even steps too)."""
        if steps < 1:
            raise ValueError("steps must be >= 1")
        start_gas = self._gas_target.copy()
        end_gas = None if pressure is None else pressure.arrays(self.batch_size)
        start_targets = {n: self._dof_target[:, d].copy() for d, n in enumerate(self.dof_names)}
        start_load = self._load
        end_targets = {n: _per_problem(v, self.batch_size, n) for n, v in (targets or {}).items()}
        out = []
        it = range(1, steps + 1)
        if progress:
            from tqdm.auto import tqdm

            it = tqdm(it, desc="load steps", leave=False)
        for s in it:
            frac = s / steps
            tg = {n: start_targets[n] + frac * (v - start_targets[n]) for n, v in end_targets.items()}
            bl = None if body_load is None else start_load.interpolate(body_load, frac, self.batch_size)
            gas = None
            if end_gas is not None:
                law = start_gas + frac * (end_gas - start_gas)
                gas = PressureLoad(gauge_pressure=law[:, 0], pv=law[:, 1])
            out.append(self.solve(tg, bl, pressure=gas))
        return out

    # ------------------------------------------------------------------ load stepping
    def _advance(self, path: _LoadPath, barrier: bool, level_done=None) -> None:
        """Drive the load increments of ``path.todo`` to the end of their load paths.

        Every Newton pass iterates all problems whose increment is still running. With ``barrier`` the
        problems that converge or fail wait for the last one before their next increments start together
        (``solve``); without it each problem's increment is settled as soon as its Newton iterations end
        and its next one starts at the next pass. ``level_done(left)`` is called with the problems that
        left their load path (reached its end or were flagged) and returns those it gave a new one
        (``path.begin``), which continue."""
        o = self.options
        run = _NewtonRun.empty(
            self.batch_size,
            self.num_dofs,
            path.relag_every,
            max_step=o.max_step_fraction * self.mesh.diameter,
            escape=o.escape_fraction * self.mesh.diameter,
        )
        release = o.stabilization > 0 and o.stabilization_release
        relax = release and o.stabilization_relax > 0
        springs = np.ones(self.batch_size)  # fraction of the increment stabilization springs on, per problem
        waiting = np.zeros(self.batch_size, dtype=bool)
        self._begin_increments(path, run, path.todo)
        while run.working.any():
            self._newton_pass(run)
            if barrier and run.working.any():
                continue
            done = run.started & ~run.working
            if not done.any():
                continue
            run.started &= ~done
            if release:
                # an increment that converged stabilized continues without the springs, from that state;
                # only an exact equilibrium is accepted
                fresh = done & ~waiting  # (settled problems that wait for others at the barrier: not again)
                back = fresh & path.releasing
                freed, again = self._relax(path, run, fresh) if relax else (fresh & run.ok & ~back, None)
                moved = freed if again is None else freed | again
                # a proximal loop with weakened springs (relax decay) that ended: full springs again
                weak = fresh & ~moved & ~back & (springs != 1.0)
                if moved.any() or back.any() or weak.any():
                    path.held_newton[moved] += run.iters[moved]
                    path.held_linear[moved] += run.lin_iters[moved]
                    path.releasing[freed] = True
                    path.releasing[back] = False
                    springs[freed] = 0.0
                    springs[back | weak] = 1.0
                    rescaled = weak.copy()
                    if again is not None:
                        rescaled |= again & (springs != path.spring_scale)
                        springs[again] = path.spring_scale[again]
                        self._copy_rows(self._q, self._q_spring, self._active_array(freed))
                    # factors made with (without, with other) springs on the diagonal
                    self.system.forget_factors(freed | back | rescaled)
                    self._newton_begin(run, moved)
                    if freed.any() or back.any() or rescaled.any():
                        self._stabilize(springs)
                    if np.any(run.damping):
                        self._set_damping_shift(run.damping)
                    done &= ~moved
                    if barrier and moved.any():
                        waiting |= done
                        run.started |= done  # the others wait for the released ones, as in lockstep
                        continue
            waiting[:] = False
            if not done.any():
                continue
            left = self._finish_increments(path, run, done)
            again = path.todo & done
            if level_done is not None and left.any():
                again |= level_done(left)
            if again.any():
                self._begin_increments(path, run, again)
        self._exact_hessian.zero_()
        self._set_damping_shift(np.zeros(self.batch_size))

    def _relax(self, path: _LoadPath, run: _NewtonRun, done: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The proximal loop of ``stabilization_relax`` for the problems whose Newton solves ended (``done``).

        Returns ``freed`` (a stabilized solve converged: released next, from its state, which the springs'
        reference ``_q_spring`` keeps) and ``again`` (a re-referenced stabilized solve runs next: after a
        failed release from the kept stabilized solution, after a converged one from its own state, with
        the springs' reference moved there). A proximal solve that failed, or converged with springs still
        pulling harder than the Newton tolerance after the last allowed one, ends the increment as failed
        (``run.ok`` cleared); the caller bisects it as any."""
        o = self.options
        back = done & path.releasing
        proximal = done & path.relaxing
        relaxed = np.zeros_like(done)
        if (proximal & run.ok).any():
            # the springs' largest force at the converged state: no more than the Newton tolerance?
            N, R = self.mesh.num_vertices, self.rows_per_problem
            rows = np.flatnonzero(proximal & run.ok)
            q = self._host_rows(self._q, R, rows)[:, :N]
            q_spring = self._host_rows(self._q_spring, R, rows)[:, :N]
            c = self._stabilization_np[rows] * path.spring_scale[rows, None]
            spring = np.max(c * np.linalg.norm(q - q_spring, axis=2), axis=1)
            relaxed[rows] = spring <= run.tol[rows]
            log.debug("stabilization relax: springs' force %s, tolerance %s", spring[:4], run.tol[rows][:4])
        freed = (done & run.ok & ~back & ~proximal) | relaxed
        budget = path.relaxes < o.stabilization_relax
        newton_budget = self._newton_budget()
        if newton_budget.any():
            spent = path.newton_total + path.held_newton + run.iters
            budget &= (newton_budget == 0) | (spent < RELAX_BUDGET_SHARE * newton_budget)
        decay = o.stabilization_relax_decay
        retry = back & ~run.ok & budget  # the release failed: back to the stabilized solution
        # a proximal solve with weakened springs that failed: back to the last converged one, stiffer
        stiffer = proximal & ~run.ok & budget & (path.spring_scale < 1.0)
        failed = proximal & ~run.ok & ~stiffer
        more = proximal & run.ok & ~relaxed & budget
        giveup = proximal & run.ok & ~relaxed & ~budget
        run.ok[giveup] = False
        run.status[giveup] = SolveStatus.NOT_CONVERGED
        if (retry | stiffer).any():
            self._copy_rows(self._q_spring, self._q, self._active_array(retry | stiffer))
            self._unpack(self._q, self._positions, self._travel)
        if more.any():
            self._anchor(path, more)
        if decay < 1.0:
            path.spring_scale[more] = np.maximum(path.spring_scale[more] * decay, RELAX_SPRING_FLOOR)
            path.spring_scale[stiffer] = np.minimum(path.spring_scale[stiffer] / decay**2, 1.0)
        again = retry | more | stiffer
        path.relaxes[again] += 1
        path.relaxing[proximal] = False
        path.relaxing[again] = True
        if again.any() or failed.any() or giveup.any():
            log.debug(
                "stabilization relax: again %s (solves %s), released %s, failed %s (status %s), given up %s",
                np.flatnonzero(again)[:8],
                path.relaxes[again][:8],
                np.flatnonzero(relaxed)[:8],
                np.flatnonzero(failed)[:8],
                run.status[failed][:8],
                np.flatnonzero(giveup)[:8],
            )
        return freed, again

    def _anchor(self, path: _LoadPath, mask: np.ndarray) -> None:
        """The masked problems' converged stabilized states become their springs' reference and their
        friction anchor (reference positions, stick stretches, body reference placements), as a commit
        would make them, the increment's start kept for :meth:`_unanchor` (restore point, predictor)."""
        first = mask & ~path.anchored
        if first.any():
            self._copy_rows(self._q_ref, self._q_start, self._active_array(first))
        if first.any() and self.num_bodies:
            rows = np.flatnonzero(first)
            stick = self._host_rows(self._stick_stretch, self.num_contact_points * self.num_bodies, rows)
            self._stick_start.update(zip(rows.tolist(), stick))
        path.anchored |= mask
        m = self._active_array(mask)
        if self.num_bodies:
            wp.launch(
                ck.commit_stick_stretch_kernel,
                dim=(self.batch_size, self.num_contact_points, self.num_bodies),
                inputs=[*self._contact_inputs(self._positions, self._travel), m],
                device=self.device,
            )
        self._copy_rows(self._q, self._q_ref, m)
        self._copy_rows(self._q, self._q_spring, m)
        self._unpack(self._q_ref, self._positions_ref, self._travel_ref)
        self._commit_body_reference(mask)

    def _unanchor(self, mask: np.ndarray) -> None:
        """The masked (anchored) problems' reference and stick stretches back at their increment's start
        (their failed increment is then restored to it); body reference placements follow the restore."""
        self._copy_rows(self._q_start, self._q_ref, self._active_array(mask))
        self._unpack(self._q_ref, self._positions_ref, self._travel_ref)
        if self.num_bodies:
            rows = np.flatnonzero(mask)
            stick = np.stack([self._stick_start.pop(b) for b in rows.tolist()])
            self._put_rows(self._stick_stretch, self.num_contact_points * self.num_bodies, rows, stick)

    def _begin_increments(self, path: _LoadPath, run: _NewtonRun, mask: np.ndarray) -> None:
        """Start the next load increment (``path.lam_done`` -> ``path.lam_try``) of the masked problems."""
        if not mask.any():
            return
        log.debug("load increment: fractions %s -> %s", path.lam_done[mask][:4], path.lam_try[mask][:4])
        step = path.change * (path.lam_try - path.lam_done)[:, None]
        self._start_increment(step, path.lam_try, path.start, path.end, mask)
        run.snap[mask] = self._snapping[mask]  # (set with path.snapping at the attempt, and kept)
        self._newton_begin(run, mask)

    def _finish_increments(self, path: _LoadPath, run: _NewtonRun, done: np.ndarray) -> np.ndarray:
        """Settle the increments of the problems ``done`` with their Newton iterations: commit and grow the
        next increment, or restore and halve it, or flag the problem. Returns the problems that left their
        load path (reached its end or were flagged)."""
        o = self.options
        ok, fail_status = run.ok & done, run.status.copy()
        path.newton_total[done] += run.iters[done] + path.held_newton[done]
        path.linear_total[done] += run.lin_iters[done] + path.held_linear[done]
        path.held_newton[done] = 0
        path.held_linear[done] = 0
        path.relaxes[done] = 0
        path.relaxing[done] = False
        path.spring_scale[done] = 1.0
        path.residual[done] = run.residual[done]
        # an equilibrium in which a body pressed through the object between its vertices is no answer:
        # retried with smaller increments like a failed one, flagged PINCHED if it persists
        pinched = self._pinched(ok)
        fail_status[pinched] = SolveStatus.PINCHED
        good = ok & ~pinched
        bad = done & ~good
        left = np.zeros(self.batch_size, dtype=bool)
        anchored = done & path.anchored
        path.anchored[done] = False
        if good.any():
            step = path.lam_try - path.lam_done
            self._commit(good, path.change * step[:, None])
            if (good & anchored).any():
                # the predictor's increment runs from the increment's start, not from the moved anchor
                self._difference_rows(
                    self._q, self._q_start, self._active_array(good & anchored), self._last_increment
                )
                for b in np.flatnonzero(good & anchored).tolist():
                    self._stick_start.pop(b, None)
            path.lam_done[good] = path.lam_try[good]
            path.snapping[good] = False
            finished = good & (path.lam_done >= 1.0)
            self._load_steps[finished] += 1
            snapped = finished & path.snap_tried  # the load step reached past its runaways
            if snapped.any():
                self.snaps[snapped] += 1
                for b in np.flatnonzero(snapped).tolist():
                    log.info("problem %d snapped: reached its load step past a force maximum", b)
            path.todo &= ~finished
            left |= finished
            grow = good & ~finished
            path.lam_try[grow] = np.minimum(1.0, path.lam_done[grow] + 2.0 * step[grow])
        if bad.any():
            if (bad & anchored).any():
                self._unanchor(bad & anchored)
            snap = np.zeros(self.batch_size, dtype=bool)  # problems that now get their snap attempt
            snap_failed = bad & path.snapping  # a failed snap attempt ends the problem
            path.snapping[bad] = False
            if o.force_maximum_runaway > 0:
                # (the failed attempts' travels, before they are restored)
                stalled = bad & (fail_status == SolveStatus.NOT_CONVERGED)
                path.runaways[self._force_runaway(path, stalled)] += 1
                maximum = stalled & ((path.runaways >= o.force_maximum_attempts) | snap_failed)
                if o.force_maximum_snap > 0:
                    # one more attempt at the same increment with force_maximum_snap Newton iterations
                    snap = maximum & ~path.snap_tried
                    path.snapping[snap] = True
                    path.snap_tried[snap] = True
                    self._snapping[snap] = True  # and every later increment of the problem
                    maximum &= ~snap
                fail_status[maximum] = SolveStatus.FORCE_MAXIMUM
            self._restore(bad)
            if (bad & anchored).any():
                self._commit_body_reference(bad & anchored)  # (placed by the restored travels)
            self.system.forget_factors(bad)  # made at states of the failed increment
            path.bisections[bad] += 1
            tiny = (path.lam_try - path.lam_done) < 2.0**-o.max_load_bisections
            giveup = bad & (
                (path.bisections > 4 * o.max_load_bisections)
                | tiny
                | (fail_status == SolveStatus.NONFINITE)
                | (fail_status == SolveStatus.FORCE_MAXIMUM)
                | snap_failed
            )
            for b in np.nonzero(giveup)[0]:
                self.status[b] = fail_status[b]
                log.info(
                    "problem %d flagged %s at load fraction %.4g",
                    b,
                    SolveStatus(fail_status[b]).name,
                    path.lam_done[b],
                )
            path.todo &= ~giveup
            left |= giveup
            retry = bad & ~giveup
            halve = retry & ~snap  # (the snap attempt retries the same increment)
            path.lam_try[halve] = 0.5 * (path.lam_done[halve] + path.lam_try[halve])
            if o.relag_friction_on_retry:  # from the k-th failed attempt of the step on (True: k = 1)
                path.relag_every |= halve & (path.bisections >= int(o.relag_friction_on_retry))
            # the snap attempt freezes its friction lags after the first iterations, as a first attempt does
            path.relag_every[snap] = False
        newton_budget = self._newton_budget()  # (with the snap attempts' allowance granted above)
        if newton_budget.any():
            spent = path.todo & done & (newton_budget > 0) & (path.newton_total >= newton_budget)
            for b in np.nonzero(spent)[0]:
                self.status[b] = SolveStatus.NOT_CONVERGED
                log.info(
                    "problem %d flagged NOT_CONVERGED at load fraction %.4g: %d Newton iterations spent",
                    b,
                    path.lam_done[b],
                    path.newton_total[b],
                )
            path.todo &= ~spent
            left |= spent
        return left

    def _newton_budget(self) -> np.ndarray:
        """(B,) Newton budget of each problem's current load step (0: none): ``max_newton_first_step`` for a
        problem that has not finished a load step since its rest state, else ``max_newton_per_solve``; plus
        ``force_maximum_snap`` for a problem that made a snap attempt."""
        o = self.options
        first = o.max_newton_per_solve if o.max_newton_first_step is None else o.max_newton_first_step
        budget = np.where(self._load_steps == 0, first, o.max_newton_per_solve)
        # a problem that made a force_maximum_snap attempt gets its iterations on top of a finite budget
        return np.where((budget > 0) & self._snapping, budget + o.force_maximum_snap, budget)

    def _force_runaway(self, path: _LoadPath, mask: np.ndarray) -> np.ndarray:
        """(B,) bool: the masked problems' failed increments (their states not yet restored) raised the force
        of a force-controlled dof and ran its travel past ``force_maximum_runaway`` times what the secant
        stiffness of the problem's last converged increment predicts for that force change
        (``SolverOptions.force_maximum_runaway``). Only a dof whose last converged increment changed its
        force the same way, with travel along the force (a positive secant), is judged; a problem without
        one (the first increment of a ramp, after a reset or a copied rest state) never runs away."""
        B, D, N = self.batch_size, self.num_dofs, self.mesh.num_vertices
        out = np.zeros(B, dtype=bool)
        force = np.array([mode == "force" for mode in self.dof_mode], dtype=bool)
        if not (mask.any() and force.any()) or self._last_change.shape[1] < D:
            return out
        rows = np.flatnonzero(mask)
        # the failed attempt's travel
        moved = self._host_rows(self._travel, D, rows) - self._host_rows(self._travel_ref, D, rows)
        load = path.change[rows, :D] * (path.lam_try - path.lam_done)[rows, None]  # its force change
        last_load = self._last_change[rows, :D]  # the last converged increment's force change ...
        last_moved = self._host_rows(self._last_increment, self.rows_per_problem, rows)[:, N : N + D, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            # ... and travel: the travel the secant predicts for this attempt is load * last_moved / last_load
            judged = force[None] & (load * last_load > 0) & (last_moved * last_load > 0)
            ratio = np.where(judged, moved * last_load / (load * last_moved), 0.0)
        out[rows] = np.any(ratio > self.options.force_maximum_runaway, axis=1)
        return out

    # ------------------------------------------------------------------ Newton
    def _stabilize(self, on: np.ndarray) -> None:
        """The increment stabilization springs per problem at fraction ``on`` (0: off, 1: full; energy,
        gradient, Hessian)."""
        N = self.mesh.num_vertices
        stab = self._stabilization_np * on[:, None]
        self._stabilization.assign(stab.reshape(-1))
        shift = self._diag_shift_base
        shift[:, :N, :] = (self._regularization_np + stab)[:, :, None]
        self._diag_shift.assign(shift.reshape(-1, 3))
        self._shift_damping[:] = 0.0

    def _set_damping_shift(self, damping: np.ndarray) -> None:
        """Diagonal shift <- regularization (and springs) + Levenberg-Marquardt ``damping`` (B,) E h.

        Writes only the problems whose damping changed (the whole batch's shift is B x 3 (N + D) floats,
        uploaded at nearly every Newton pass of the exact-Hessian solves otherwise)."""
        rows = np.flatnonzero(damping != self._shift_damping)
        if not len(rows):
            return
        shift = self._diag_shift_base[rows] + damping[rows, None, None] * self._damping_scale[rows]
        self._put_rows(self._diag_shift, self.rows_per_problem, rows, shift)
        self._shift_damping[rows] = damping[rows]

    def _newton_begin(self, run: _NewtonRun, mask: np.ndarray) -> None:
        """Start the Newton iterations of the masked problems at their current state and loads.

        Friction normal forces are re-lagged at each of the first iterations of an increment (contacts and
        their friction establish themselves), then frozen so Newton minimizes one smooth potential (vertices
        at the rim of a contact patch would otherwise toggle the friction law between iterations). A state
        that converges with frozen lags is accepted only if its own normal forces match the lags."""
        if not mask.any():
            return
        B, D = self.batch_size, self.num_dofs
        run.working |= mask
        run.started |= mask
        o = self.options
        # (the stabilized solve, its release and relax solves of a snap attempt all get its cap)
        run.cap[mask] = np.where(
            run.snap[mask], max(o.force_maximum_snap, o.max_newton_iterations), o.max_newton_iterations
        )
        run.ok[mask] = False
        run.status[mask] = SolveStatus.NOT_CONVERGED
        run.passes[mask] = 0
        run.iters[mask] = 0
        run.lin_iters[mask] = 0
        run.residual[mask] = np.inf
        run.relag[mask] = True
        run.relags[mask] = 0
        run.last_relag[mask] = 0
        run.stale[mask] = False
        run.stale_step[mask] = False
        self._relag_has_residual[mask] = False
        run.exact[mask] = 0
        self._exact_hessian.assign(run.exact)
        if np.any(run.damping[mask]):
            run.damping[mask] = 0.0
            self._set_damping_shift(run.damping)
        if D:
            run.dof_targets[mask] = np.abs(self._dof_force.numpy()[: B * D].reshape(B, D))[mask]

    def _newton_pass(self, run: _NewtonRun) -> None:
        """One Newton iteration of every problem in ``run.working``; problems that converge or fail leave it
        (``run.ok``, ``run.status``)."""
        o = self.options
        B = self.batch_size
        sysm = self.system
        working = run.working
        # a safety bound on the passes of one Newton solve (each problem's own budgets end it first)
        working &= run.passes < (run.cap + 1) * (o.max_friction_relags + 1)
        if not working.any():
            return
        run.passes[working] += 1
        self.newton_passes += 1
        self._relag_friction(run.relag & working, accelerate=run.stale if o.friction_relaxation else None)
        run.stale = np.zeros(B, dtype=bool)
        run.relag = working & ((run.iters < o.friction_relag_iterations) | run.relag_every)
        active = self._active_array(working)
        assembled = working.copy()
        self._assemble(active)
        res_arr = self._newton_scales[2]
        wp.launch(
            kk.newton_rhs_kernel,
            dim=(B, self.rows_per_problem),
            inputs=[sysm.gradient, self._free, active, self.rows_per_problem, sysm.rhs, res_arr],
            device=self.device,
        )
        # force scale, load scale and residual in one read (on the CPU numpy() is a view: copied)
        fscale, lscale, res = self._newton_scales.numpy().copy()
        previous = run.residual.copy()
        run.residual[working] = res[working]
        scale = np.maximum(np.maximum(fscale, lscale), run.dof_targets.max(axis=1, initial=0.0))
        tol = o.rtol * scale + self._newton_atol
        run.tol[working] = tol[working]
        nonfinite = working & ~np.isfinite(res)
        if nonfinite.any():
            run.status[nonfinite] = SolveStatus.NONFINITE
            working &= ~nonfinite
        conv = working & (res <= tol)
        # (problems re-lagged at every iteration were re-lagged at this very state: consistent)
        frozen = conv & (run.iters >= o.friction_relag_iterations) & ~run.relag_every

        def relag_stale(checked: np.ndarray, tolerance: np.ndarray) -> np.ndarray:
            """Problems of ``checked`` whose lags are inconsistent beyond ``tolerance``, within their re-lag
            budget: re-lagged (Aitken-extrapolated) at the next pass, each starting a new Newton solve of
            the updated potential with its own iteration budget."""
            stale = self._friction_inconsistent(checked, tolerance) & (run.relags < o.max_friction_relags)
            run.relags[stale] += 1
            run.relag |= stale
            run.last_relag[stale] = run.iters[stale]
            run.stale |= stale
            return stale

        if frozen.any():
            # lag consistency: the converged state's own friction capacities must equal the lagged ones
            conv &= ~relag_stale(frozen, tol)
        if o.friction_lag_check > 1:
            # nearly converged with frozen lags: a lag error well above the residual will not go away in the
            # last iterations (the normal forces move by about the residual): re-lag now
            near = working & ~conv & (res <= o.friction_lag_check * tol)
            near &= (run.iters >= o.friction_relag_iterations) & ~run.relag_every & ~run.relag
            if near.any():
                relag_stale(near, 10.0 * res)
        if log.isEnabledFor(logging.DEBUG):
            b0 = int(np.argmax(working))
            log.debug("newton it %d problem %d residual %.3e tol %.3e", run.iters[b0], b0, res[b0], tol[b0])
        if o.stabilization > 0 and conv.any():
            stab = self._stabilization_force.numpy()
            self._stabilization_at_convergence[conv] = stab[conv]
        run.ok |= conv
        working &= ~conv
        if not working.any():
            return
        # a problem out of Newton iterations since its last re-lag fails this increment (the others go on)
        working &= (run.iters - run.last_relag) < run.cap
        if not working.any():
            return
        run.iters[working] += 1
        # rhs of problems that are done is zero: rebuild it for the working set only
        if not np.array_equal(working, assembled):
            active = self._active_array(working)
            wp.launch(
                kk.newton_rhs_kernel,
                dim=(B, self.rows_per_problem),
                inputs=[sysm.gradient, self._free, active, self.rows_per_problem, sysm.rhs, res_arr],
                device=self.device,
            )
        # inexact Newton (Eisenstat-Walker): solve only as accurately as the nonlinear residual warrants
        with np.errstate(divide="ignore", invalid="ignore"):
            ew = np.where(np.isfinite(previous), 0.9 * (res / previous) ** 2, 0.1)
            floor = 0.5 * tol / res
        forcing = np.clip(np.maximum(ew, floor), o.cg_rtol, 0.1)
        # safeguard: where Newton stagnates, solve exactly (CG resolves soft and runaway modes last)
        forcing[res > 0.9 * previous] = o.cg_rtol
        linear_rtol = float(forcing[working].min())
        refactor = working
        damping = run.damping
        if self._reuse_factors:
            # keep a factorization while the residual contracts fast (first step of an increment: its
            # predecessor's), at most max_factor_reuse further steps and with the damping it was made with
            slow = np.isfinite(previous) & ~(res <= o.factor_reuse_contraction * previous)
            worn = self._factor_steps > self._max_factor_reuse
            refactor = working & (slow | worn | run.stale_step | (damping != self._factor_damping))
        sysm.extra_increment = None
        gas_k = np.where(working, self._gas_k, 0.0) if self.pressure_surface is not None else None
        gas_u = self._gas_direction(gas_k) if gas_k is not None and np.any(gas_k > 0) else None
        if gas_u is not None and self.linear_solver in ("dense", "banded", "dense_banded"):
            sysm.extra_rhs = gas_u  # the gas stiffness's direction, solved in the step's substitutions
        if o.exact_hessian:
            # an exact Hessian that is not positive definite gets no step (zero increment: the line search
            # rejects it) and the Levenberg-Marquardt damping below, instead of an LU step
            sysm.report_indefinite = working & (run.exact == 1)
        try:
            # the right-hand side is not zero exactly for the working problems (their residual is above
            # a positive tolerance; the others' rows were zeroed above)
            n_lin, _ = self._linear_solve(linear_rtol, refactor, problems=working)
        finally:
            sysm.extra_rhs = None
            sysm.report_indefinite = None
        fresh = working & (sysm.fresh_factor if self._reuse_factors else True)
        self._factor_steps[working] += 1
        self._factor_steps[fresh] = 1
        self._factor_damping[fresh] = damping[fresh]
        if gas_u is not None:
            n_lin += self._gas_rank_one(gas_k, gas_u, linear_rtol)
        run.lin_iters[working] += n_lin
        failed, first_trial, alpha = self._line_search(working, run.max_step)
        # a stale factorization's step that the line search rejects or shortens is no verdict on the
        # Hessian (no damping, no stall): the next step factors anew (a rejected one from the same state)
        run.stale_step = working & ~fresh & ((failed == 1) | (alpha < first_trial))
        failed[run.stale_step & (failed == 1)] = 0
        if log.isEnabledFor(logging.DEBUG):
            log.debug("  step %.3e line search %s", alpha[int(np.argmax(working))], failed[working][:4])
        nonfinite_step = failed == 2
        run.status[nonfinite_step] = SolveStatus.NONFINITE
        if o.exact_hessian:
            # trust the exact Hessian after a full step that lowered the residual; when its step fails
            # or is cut back by the line search (a step shortened to max_step is not), retry from the
            # unchanged state with Levenberg-Marquardt damping, then with the projected Hessian
            exact = run.exact
            full = alpha >= first_trial
            lost = working & fresh & (exact == 1) & ((failed == 1) | ~full)
            failed[lost] = 0
            before = damping.copy()
            damp = lost & (damping < LM_MAX)
            damping[damp] = np.maximum(10.0 * damping[damp], LM_START)
            exact[lost & ~damp] = 0
            damping[lost & ~damp] = 0.0
            # an accepted full damped step widens the trust region whatever the residual did (a sliding
            # body's residual stays put while its energy falls; a fixed damping would make it crawl)
            damping[working & fresh & ~lost & full & (exact == 1)] /= 3.0
            good = working & ~lost & full & (res < previous)
            damping[damping < LM_MIN] = 0.0
            exact[good] = 1
            self._exact_hessian.assign(exact)
            if np.any(damping != before):
                self._set_damping_shift(damping)
        # a failed line search this close to the tolerance is round-off: accept the state
        stalled = failed == 1
        near = stalled & (run.residual <= 1e3 * tol)
        run.ok |= near
        working &= ~(stalled | nonfinite_step)
        # escape: the object moved too far within one increment
        drift = self._drift
        drift.zero_()
        wp.launch(
            kk.vertex_drift_kernel,
            dim=(B, self.mesh.num_vertices),
            inputs=[self._q, self._q_ref, self.mesh.num_vertices, self.rows_per_problem, drift],
            device=self.device,
        )
        esc = working & (drift.numpy() > run.escape)
        run.status[esc] = SolveStatus.ESCAPED
        working &= ~esc

    def _linear_solve(
        self, rtol: float, refactor: np.ndarray | None = None, problems: np.ndarray | None = None
    ) -> tuple[int, float]:
        """H increment = rhs with the configured linear solver; returns (iterations, residual; nan where a
        factorizing solver was spared computing it: the Newton loop checks its own residual and step).
        ``refactor``: problems whose stored factorization is out of date (direct and dense solvers; None:
        none, a second right-hand side of the same matrices). ``problems`` (B,) bool: exactly those whose
        right-hand side is not zero, where the caller knows them (the PyTorch solvers then need not read
        the right-hand sides from the device); None: found from the right-hand sides."""
        o, sysm = self.options, self.system
        todo = None if problems is None else np.flatnonzero(problems).tolist()
        if self.linear_solver == "cg":
            return sysm.solve_cg(rtol, o.cg_max_iterations)
        if self.linear_solver == "amg":
            return sysm.solve_amg(self._near_nullspace, rtol, o.cg_max_iterations)
        if self.linear_solver == "dense":
            return sysm.solve_dense(refactor, residual=False, todo=todo)
        if self.linear_solver == "banded":
            return sysm.solve_banded(refactor, todo=todo, residual=False)
        if self.linear_solver == "dense_banded":
            return sysm.solve_dense_banded(refactor, o.banded_min_problems, residual=False, todo=todo)
        return sysm.solve_direct(refactor)

    def _line_search(self, working: np.ndarray, max_step: float):
        """Armijo backtracking on Pi per problem; updates the state. Returns per problem 0 (accepted) or
        1 (no acceptable step), the first step length tried (1, or less where the step is shortened to
        ``max_step``) and the accepted step length (0 where none).

        The energies of ``SolverOptions.line_search_trials`` = T step lengths per problem are evaluated in
        one pass (the first pass holds the current state and T - 1 halvings, later ones T halvings each);
        the accepted step is the largest that passes, as one-at-a-time backtracking accepts."""
        B, R, T = self.batch_size, self.rows_per_problem, self._line_search_trials
        sysm = self.system
        stats = self._step_stats
        stats.zero_()
        wp.launch(
            kk.step_stats_kernel,
            dim=(B, R),
            inputs=[sysm.rhs, sysm.increment, self.mesh.num_vertices, R, stats[0], stats[1], stats[2]],
            device=self.device,
        )
        slope_np, vmax, dmax = stats.numpy()
        biggest = np.maximum(vmax, dmax)
        alpha = np.where(working, np.minimum(1.0, max_step / np.maximum(biggest, 1e-300)), 0.0)
        sc = self._self_contact
        if sc is not None and sc.barrier and working.any():
            # no pair of the self-contact barrier passes through zero distance between trial states
            bound = sc.step_bound(self._positions, sysm.increment, R, self._active_array(working))
            alpha = np.minimum(alpha, bound)
        first_trial = alpha.copy()
        result = np.zeros(B, dtype=int)
        searching = working.copy()
        bad_dir = searching & ~(slope_np < 0)
        result[bad_dir] = 1
        searching &= ~bad_dir
        alpha[bad_dir] = 0.0
        accepted = np.zeros(B, dtype=bool)
        e_accepted = np.zeros(B)
        e0 = None
        if T == 1:
            e0 = self._energy_at(self._q, self._positions, self._travel, self._active_array(searching))
        halvings = 0  # step lengths tried so far (alpha = first_trial / 2^halvings)
        while searching.any() and halvings < 60:
            # slot 0 of the first pass is the current state (step 0) when several trials share a pass
            first = 1 if e0 is None else 0
            n = min(T - first, 60 - halvings)
            steps = np.zeros((first + n, B))
            for j in range(n):
                steps[first + j] = np.where(searching, alpha * 0.5**j, 0.0)
            # only the problems still searching (the others' energies are not needed: on the CPU every
            # problem's energy costs its own kernel time)
            energies = self._energies_along(steps, self._active_array(searching))
            if e0 is None:
                e0 = energies[0]
            for j in range(n):
                e1 = energies[first + j]
                trial = alpha * 0.5**j
                slack = 1e-12 * (np.abs(e0) + np.abs(e1)) + 1e-300
                good = searching & np.isfinite(e1) & (e1 <= e0 + 1e-4 * trial * slope_np + slack)
                alpha[good] = trial[good]
                e_accepted[good] = e1[good]
                accepted |= good
                searching &= ~good
            alpha[searching] *= 0.5**n
            halvings += n
        result[searching] = 1
        alpha[~accepted] = 0.0
        if sc is not None and sc.barrier and e0 is not None and accepted.any():
            self._refine_full_steps(accepted & (alpha >= first_trial), alpha, e0, e_accepted, slope_np)
        self._step.assign(alpha)
        # q += alpha dq in place (each row reads and writes only itself)
        wp.launch(
            kk.trial_state_kernel,
            dim=(B, R),
            inputs=[self._q, sysm.increment, self._step, R, B, self._q],
            device=self.device,
        )
        self._unpack(self._q, self._positions, self._travel)
        return result, first_trial, alpha

    def _energies_along(self, steps: np.ndarray, active) -> np.ndarray:
        """(n, B) Pi at q + t dq for each of the n <= ``line_search_trials`` rows of step lengths t (``steps``
        (n, B); dq the last Newton direction, ``system.increment``) in one set of launches, for the
        problems flagged in ``active`` (an ``_active_array``; 0 for the others). The trial states stay in
        the trial arrays (state t B + b is row t of problem b)."""
        B, R, T = self.batch_size, self.rows_per_problem, self._line_search_trials
        trial = np.zeros((T, B))
        trial[: len(steps)] = steps
        self._trial_step.assign(trial.reshape(-1))
        states = len(steps) * B
        wp.launch(
            kk.trial_state_kernel,
            dim=(states, R),
            inputs=[self._q, self.system.increment, self._trial_step, R, B, self._q_trial],
            device=self.device,
        )
        self._unpack(self._q_trial, self._positions_trial, self._travel_trial, states)
        return self._energies_at(self._q_trial, self._positions_trial, self._travel_trial, active, len(steps))

    def _refine_full_steps(self, full: np.ndarray, alpha: np.ndarray, e0, e1, slope) -> None:
        """Model "barrier": where a full step was accepted (``full``) but the energy along it curves more
        than Newton's model (the minimum of the parabola through Pi(0), Pi'(0) = ``slope`` and Pi(alpha) =
        ``e1`` lies below 0.8 of the step), take the parabola's minimum instead if its energy is lower
        (``alpha`` updated in place; one energy pass more). The barrier's Hessian jumps where a pair's
        closest point moves between a face, an edge and a corner; across such a boundary full Newton steps
        overshoot back and forth (a thin ring's walls meeting at two vertices: full steps twice too long
        every iteration, the residual falling ~2 % an iteration until the step's budget ran out; with this,
        the step converges in 24 iterations: measured, ``benchmarks/fem_self_contact_barrier_s50.md``)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            curvature = (e1 - e0 - slope * alpha) / alpha**2
            best = np.where(full & (curvature > 0), -slope / (2.0 * curvature), np.inf)
        shorter = full & (best < 0.8 * alpha) & (best > 0)
        if not shorter.any():
            return
        steps = np.where(shorter, best, 0.0)[None]
        e = self._energies_along(steps, self._active_array(shorter))[0]
        lower = shorter & np.isfinite(e) & (e < e1)
        alpha[lower] = best[lower]

    def _start_increment(self, change, lam, start, end, mask):
        """Initial state of the masked problems' next increment: the predictor, then the loads. A predicted
        state that inverts a Neo-Hookean element (infinite energy) falls back to the last converged one, and
        so does one that (with self-contact) puts a surface vertex deeper behind another part of the surface
        than :data:`PREDICTED_SELF_PENETRATION` of the self-contact depth: the extrapolation runs the object
        through itself towards where its pairs stop holding (there the penalty's candidates drop and Newton
        stalls: a thin ring squeezed flat, its inner walls about to meet,
        ``benchmarks/fem_self_contact_predictor_cpu_s49.md``). With the "barrier" model the straight path
        from the last converged state to the predicted one is checked instead (the line search's step
        bound): a prediction that would carry a pair through zero distance falls back."""
        self._predict(change, mask)
        self._apply_increment(lam, start, end, mask)
        fallback = np.zeros(self.batch_size, dtype=bool)
        if self._barrier:
            energy = self._energy_at(self._q, self._positions, self._travel, self._active_array(mask))
            fallback |= mask & ~np.isfinite(energy)
        sc = self._self_contact
        if sc is not None and sc.barrier:
            # model "barrier": the straight path from the last converged state to the predicted one must not
            # run a pair through zero distance (its energy is finite again beyond: tunnelling)
            m = self._active_array(mask)
            sc.update_pairs(self._positions_ref)
            self._difference_rows(self._q, self._q_ref, m, self._q_trial)  # the path (scratch rows)
            bound = sc.step_bound(self._positions_ref, self._q_trial, self.rows_per_problem, m)
            fallback |= mask & (bound < 1.0)
            # the friction of the increment: lagged at its start, the last converged state
            sc.lag_friction(self._positions_ref, self._youngs, self._self_contact_law()[0], m)
        elif sc is not None:  # the predicted state's penetrations (its forces are not needed)
            self._unpack(self._q, self._positions, self._travel)
            penetration = sc.penetration(self._positions, self._youngs, *self._self_contact_law())
            deep = penetration.max(axis=1) > PREDICTED_SELF_PENETRATION * sc.depth
            fallback |= mask & deep
        if fallback.any():
            self._predict(change, mask, extrapolate=mask & ~fallback)
            self._apply_increment(lam, start, end, mask)

    def _predict(self, change: np.ndarray, mask: np.ndarray, extrapolate: np.ndarray | None = None):
        """Initial guess of the masked problems' increment: q = q_ref + r * (last converged increment of q),
        where r is the size of this load change relative to the last one (0 unless both changes are
        parallel, and 0 outside ``extrapolate``, default ``mask``). Other problems' states are untouched."""
        ratio = np.zeros(self.batch_size)
        if extrapolate is None:
            extrapolate = mask
        e = np.nonzero(extrapolate)[0]
        if self._last_change.shape == change.shape and e.size:
            now, last = change[e], self._last_change[e]
            dot = np.einsum("bi,bi->b", now, last)
            norms = np.linalg.norm(now, axis=1) * np.linalg.norm(last, axis=1)
            parallel = (norms > 0) & (dot > 0.999 * norms)
            ratio[e[parallel]] = np.minimum(
                2.0, dot[parallel] / np.einsum("bi,bi->b", last[parallel], last[parallel])
            )
        self._step.assign(ratio)
        wp.launch(
            kk.predicted_state_kernel,
            dim=(self.batch_size, self.rows_per_problem),
            inputs=[
                self._q_ref,
                self._last_increment,
                self._step,
                self._active_array(mask),
                self.rows_per_problem,
                self._q,
            ],
            device=self.device,
        )

    def _commit(self, mask: np.ndarray, change: np.ndarray):
        """Accept the masked problems' states as converged: friction memory, predictor data, reference."""
        m = self._active_array(mask)
        self._difference_rows(self._q, self._q_ref, m, self._last_increment)
        if self._last_change.shape != change.shape:
            self._last_change = np.zeros_like(change)
        self._last_change[mask] = change[mask]
        if self.num_bodies:
            wp.launch(
                ck.commit_stick_stretch_kernel,
                dim=(self.batch_size, self.num_contact_points, self.num_bodies),
                inputs=[
                    *self._contact_inputs(self._positions, self._travel),
                    m,
                ],
                device=self.device,
            )
        self._copy_rows(self._q, self._q_ref, m)
        if self._q_spring is not self._q_ref:
            self._copy_rows(self._q, self._q_spring, m)
        self._unpack(self._q_ref, self._positions_ref, self._travel_ref)
        self._commit_body_reference(mask)

    def _restore(self, mask: np.ndarray):
        m = self._active_array(mask)
        self._copy_rows(self._q_ref, self._q, m)
        if self._q_spring is not self._q_ref:
            self._copy_rows(self._q_ref, self._q_spring, m)
        self._unpack(self._q, self._positions, self._travel)

    def _difference_rows(self, a: wp.array, b: wp.array, active: wp.array, out: wp.array) -> None:
        """out <- a - b for the problems flagged in ``active`` (an ``_active_array``), B x R vec3d arrays."""
        wp.launch(
            kk.masked_difference_kernel,
            dim=(self.batch_size, self.rows_per_problem),
            inputs=[a, b, active, self.rows_per_problem, out],
            device=self.device,
        )

    def _copy_rows(self, src: wp.array, dst: wp.array, active: wp.array) -> None:
        """dst <- src for the problems flagged in ``active`` (an ``_active_array``), B x R vec3d arrays."""
        wp.launch(
            kk.copy_problems_kernel,
            dim=(self.batch_size, self.rows_per_problem),
            inputs=[src, active, self.rows_per_problem, dst],
            device=self.device,
        )

    # ------------------------------------------------------------------ outputs
    def _lump_point_contacts(self, fn: np.ndarray, ff: np.ndarray, stick: np.ndarray):
        """Per surface vertex, from one body's (n, P) point normal forces, (n, P, 3) friction forces and
        (n, P) stick flags: the forces lumped with the points' barycentric weights (sum_p w_pi f_p, so sums
        over the surface are kept) and sticking where the vertex carries normal force and every loaded point
        it shares in sticks."""
        n, S = fn.shape[0], self.num_surface
        w, surf = self.contact_point_weights, self._point_surface  # (P, 3)
        cn, cf = np.zeros((n, S)), np.zeros((n, S, 3))
        slipping = np.zeros((n, S))
        for i in range(3):
            np.add.at(cn.T, surf[:, i], (w[:, i] * fn).T)
            np.add.at(cf.transpose(1, 0, 2), surf[:, i], (w[:, i, None] * ff).transpose(1, 0, 2))
            np.add.at(slipping.T, surf[:, i], (w[:, i] * ((fn > 0) & ~stick)).T)
        return cn, cf, (cn > 0) & (slipping == 0)

    def _results(self, load_fraction, newton, linear, residual, rows=None) -> Equilibrium:
        """The equilibria of all problems, or of the problems ``rows`` (integer indices) only: their
        stresses are computed and their fields copied and post-processed."""
        B, N, M = self.batch_size, self.mesh.num_vertices, self.mesh.num_tets
        K, P = self.num_bodies, self.num_contact_points
        rows = np.arange(B) if rows is None else np.asarray(rows)
        n = len(rows)
        dev = self.device
        tet_stress = wp.zeros(max(n * M, 1), dtype=wp.mat33d, device=dev)
        energy = wp.zeros(max(n, 1), dtype=wp.float64, device=dev)
        inverted = wp.zeros(max(n, 1), dtype=wp.int32, device=dev)
        wp.launch(
            ek.tet_stress_kernel,
            dim=(n, M),
            inputs=[
                self._positions,
                self._tets,
                self._rest_inverse,
                self._volume,
                self._mu,
                self._lam,
                self._model,
                N,
                wp.array(rows.astype(np.int32), dtype=wp.int32, device=dev),
                tet_stress,
                energy,
                inverted,
            ],
            device=dev,
        )
        vstress = wp.zeros(max(n * N, 1), dtype=wp.mat33d, device=dev)
        wp.launch(
            ek.vertex_von_mises_kernel,
            dim=(n, M),
            inputs=[tet_stress, self._tets, self._volume, self._vertex_weight, N, vstress],
            device=dev,
        )
        vm = wp.zeros(max(n * N, 1), dtype=wp.float64, device=dev)
        wp.launch(ek.von_mises_kernel, dim=n * N, inputs=[vstress, vm], device=dev)

        # reaction forces on fixed components: the gradient of Pi there (before constraints); the assembly
        # also gives the cavity volume's gradient (the gas force), so without either it is skipped
        R = self.rows_per_problem
        reaction = np.zeros((len(rows), N, 3))
        if self.fixed_mask.any() or self.pressure_surface is not None:
            # only the reported problems (the next Newton pass assembles the iterating ones anew)
            mask = np.zeros(B, dtype=bool)
            mask[rows] = True
            self._assemble(self._active_array(mask))
            grad = self._host_rows(self.system.gradient, R, rows).reshape(n, R, 3)
            reaction = np.where(self.fixed_mask[None], grad[:, :N], 0.0)
        gas = {}
        if self.pressure_surface is not None:
            vol = self.rest_cavity_volume + self._cavity_volume_change(self._positions)
            p = pk.gas_pressure(self._gas_law, vol, self.pressure_surface.external_volume)
            dv = self._host_rows(self._volume_gradient, R, rows).reshape(n, R, 3)[:, :N]
            gas = {
                "gauge_pressure": p[rows],
                "cavity_volume": vol[rows],
                "pressure_force": p[rows, None, None] * dv,
            }

        q = self._host_rows(self._q, R, rows).reshape(n, R, 3)
        travel = {n: q[:, N + d, 0].copy() for d, n in enumerate(self.dof_names)}
        body_force, body_torque, cn, cf, cs = {}, {}, {}, {}, {}
        dof_force = {n: np.zeros(len(rows)) for n in self.dof_names}
        max_pen = np.zeros(len(rows))
        if K:
            self._contact_state(self._positions, self._travel)
            fn = self._host_rows(self._c_force, P * K, rows).reshape(n, P, K)
            nrm = self._host_rows(self._c_normal, P * K, rows).reshape(n, P, K, 3)
            ff = self._host_rows(self._c_friction, P * K, rows).reshape(n, P, K, 3)
            st = self._host_rows(self._c_stick, P * K, rows).reshape(n, P, K).astype(bool)
            gap = self._host_rows(self._c_gap, P * K, rows).reshape(n, P, K)
            max_pen = np.maximum(0.0, -gap.min(axis=(1, 2)))
            x = self._host_rows(self._positions, N, rows).reshape(n, N, 3)
            sampled = self.options.contact_subdivisions > 1
            if sampled:  # the contact points' positions
                pos = np.einsum("bpij,pi->bpj", x[:, self.contact_point_vertices], self.contact_point_weights)
            else:
                pos = x[:, self.mesh.surface_vertices]
            rot, origin, axes = self._world_frames()
            origin, axes = origin[rows], axes[rows]
            for k, body in enumerate(self.bodies):
                on_vertex = fn[:, :, k, None] * nrm[:, :, k] + ff[:, :, k]  # force of the body on the object
                f_body = -on_vertex.sum(axis=1)
                d = self._body_dof[k]
                placed = origin[:, k] + (travel[self.dof_names[d]][:, None] if d >= 0 else 0.0) * axes[:, k]
                body_force[body.name] = f_body
                body_torque[body.name] = -np.cross(pos - placed[:, None], on_vertex).sum(axis=1)
                if sampled:
                    cn[body.name], cf[body.name], cs[body.name] = self._lump_point_contacts(
                        fn[:, :, k], ff[:, :, k], st[:, :, k]
                    )
                    continue
                cn[body.name] = fn[:, :, k].copy()
                cf[body.name] = ff[:, :, k].copy()
                cs[body.name] = st[:, :, k] & (fn[:, :, k] > 0)
                if d >= 0:
                    # the body pushes the object along its axis: -(force on the body) . axis
                    dof_force[self.dof_names[d]] += -np.einsum("bi,bi->b", f_body, axes[:, k])
        ts = None
        if self.options.record_tet_stress:
            ts = tet_stress.numpy()[: n * M].reshape(n, M, 3, 3).copy()
        return Equilibrium(
            mesh=self.mesh,
            status=self.status[rows],
            load_fraction=load_fraction[rows],
            newton_iterations=newton[rows],
            linear_iterations=linear[rows],
            residual=residual[rows],
            displacement=q[:, :N].copy(),
            travel=travel,
            dof_force=dof_force,
            vertex_stress=vstress.numpy()[: n * N].reshape(n, N, 3, 3).copy(),
            von_mises=vm.numpy()[: n * N].reshape(n, N).copy(),
            strain_energy=energy.numpy()[:n].copy(),
            inverted_tets=inverted.numpy()[:n].copy(),
            body_force=body_force,
            body_torque=body_torque,
            contact_normal_force=cn,
            contact_friction_force=cf,
            contact_sticking=cs,
            max_penetration=max_pen,
            reaction_force=reaction,
            tet_stress=ts,
            stabilization_force=self._stabilization_at_convergence[rows],
            snaps=self.snaps[rows].copy(),
            **gas,
        )
