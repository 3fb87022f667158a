"""QuasiStaticSolver.solve_stream: a queue of jobs flows through a smaller batch (a problem that finished
its job takes the next one), each job reaching the equilibria solve_sequence gives it; and the row-wise
state copy and body pose it builds on."""

import numpy as np
import pytest

from defgraspnets import fem

OFFSETS = np.array([0.0, 0.002, 0.004, 0.001, 0.003])  # m: where the pads grip along x
FORCES = np.array([1.0, 2.0, 3.0, 1.5, 2.5])  # N: grip force at the last level
STEPS = 3


def _solver(offsets=OFFSETS, materials=None, **options) -> fem.QuasiStaticSolver:
    """The off-centre pad squeeze of test_fem_solve_sequence, gripped at 20 % of its force under gravity
    (``materials``: one per problem; ``options``: SolverOptions fields)."""
    from fem_helpers import pad_squeeze_solver

    solver = pad_squeeze_solver(offsets, linear_solver="dense", **options)
    if materials is not None:
        solver.set_material(materials)
    scale = FORCES[: len(offsets)]
    solver.solve(targets={"grip": 0.2 * scale}, body_load=fem.BodyLoad(gravity=(0.0, 0.0, -9.81)))
    return solver


def _slots(batch_size: int, **options) -> fem.QuasiStaticSolver:
    """A stream's solver: ``batch_size`` problems of the pad squeeze, not gripped (every job's start state,
    body load included, is copied into its problem from a gripped template)."""
    from fem_helpers import pad_squeeze_solver

    return pad_squeeze_solver(OFFSETS[:batch_size], linear_solver="dense", **options)


def _levels(job: int, steps: int = STEPS) -> list[dict]:
    return [{"grip": float(FORCES[job] * (0.2 + 0.8 * (k + 1) / STEPS))} for k in range(steps)]


def _row(eq: fem.Equilibrium, i: int) -> fem.Equilibrium:
    return eq.take(np.array([i]))


def _assert_same(a: fem.Equilibrium, b: fem.Equilibrium) -> None:
    from fem_helpers import assert_same_squeeze

    assert_same_squeeze(a, b)


def _stream(batch_size: int, lengths, check=None, materials=None, template=None, **options):
    """Jobs j = 0..4 (job j: grasp j's levels, ``lengths[j]`` of them) through a ``batch_size`` batch whose
    problems start each job from the gripped template problem j (``materials``: the template's, one per
    job; ``template``: one made already, not changed here). Returns {(job, level): equilibrium}, the order
    of the reports and the (problem, job) starts."""
    if template is None:
        template = _solver(materials=materials, **options)
    solver = _slots(batch_size, **options)
    got, order, starts = {}, [], []

    def start(problems, jobs):
        starts.extend(zip(problems.tolist(), jobs.tolist()))
        solver.copy_state_from(template, rows=jobs, into=problems)

    def on_levels(jobs, levels, part):
        assert len(jobs) == len(levels) == part.batch_size
        for i, (j, k) in enumerate(zip(jobs.tolist(), levels.tolist())):
            assert (j, k) not in got
            got[(j, k)] = _row(part, i)
            order.append((j, k))

    jobs = [_levels(j, n) for j, n in enumerate(lengths)]
    solver.solve_stream(jobs, start, on_levels, check=check)
    return got, order, starts


def test_jobs_through_a_smaller_batch_reach_the_equilibria_of_one_sequence_per_job():
    expected = _solver().solve_sequence([{"grip": [lv[k]["grip"] for lv in map(_levels, range(5))]}
                                         for k in range(STEPS)])  # fmt: skip
    lengths = [3, 3, 2, 3, 1]  # a job may stop early: its first levels are the longer job's
    got, order, starts = _stream(2, lengths)
    assert sorted(got) == [(j, k) for j in range(5) for k in range(lengths[j])]
    for j in range(5):
        assert [k for jj, k in order if jj == j] == list(range(lengths[j]))  # a job's levels in order
        for k in range(lengths[j]):
            _assert_same(_row(expected[k], j), got[(j, k)])
    # two problems served five jobs: each new job went to a problem that had finished its last one
    assert [j for _, j in starts] == [0, 1, 2, 3, 4] and {b for b, _ in starts} == {0, 1}
    assert starts[:2] == [(0, 0), (1, 1)]


# job j's material: moduli 2.5x apart, so a problem that takes the next job also changes its material
MATERIALS = [fem.Material(e, 0.3, 1000.0) for e in (1e5, 2.5e5, 4e4, 1e5, 1.6e5)]


def test_jobs_of_other_materials_stream_as_each_alone_with_released_stabilization():
    """A problem that takes a job of another material mid-stream (copy_state_from sets its material row-wise)
    solves it as that job alone, and the problems iterating beside it, some without their stabilization
    springs (released), are not disturbed: bit for bit as one solve_sequence of the template."""
    options = {"stabilization": 1e-3, "stabilization_release": True}
    expected = _solver(materials=MATERIALS, **options).solve_sequence(
        [{"grip": [lv[k]["grip"] for lv in map(_levels, range(5))]} for k in range(STEPS)]
    )
    # these lengths start jobs 2 and 3 while the other problem iterates without its springs
    lengths = [2, 3, 1, 2, 1]
    got, _, starts = _stream(2, lengths, materials=MATERIALS, **options)
    for j, n in enumerate(lengths):
        for k in range(n):
            _assert_same(_row(expected[k], j), got[(j, k)])
    assert len(starts) == 5 and all(got[(j, 0)].newton_iterations[0] > 0 for j in range(5))


def test_a_row_wise_material_changes_only_those_problems():
    """set_material(rows=...) equals setting every problem's material with the others' unchanged, and the
    other problems solve as if it had not been called."""
    soft = fem.Material(4e4, 0.35, 1000.0)
    mats = [MATERIALS[0]] * 5
    whole, rows, plain = _solver(), _solver(), _solver()
    whole.set_material([soft if b in (1, 3) else m for b, m in enumerate(mats)])
    rows.set_material(soft, rows=[1, 3])
    assert rows.materials[1] is soft and rows.materials[0] == MATERIALS[0]
    more = {"grip": FORCES}
    a, b, c = whole.solve(targets=more), rows.solve(targets=more), plain.solve(targets=more)
    _assert_same(a.take(np.array([1, 3])), b.take(np.array([1, 3])))
    _assert_same(c.take(np.array([0, 2, 4])), b.take(np.array([0, 2, 4])))
    assert not np.allclose(b.displacement[1], c.displacement[1])  # the softer box deforms more
    with pytest.raises(ValueError, match="list of 2 \\(one per row\\) Materials"):
        rows.set_material([soft], rows=[0, 1])
    with pytest.raises(ValueError, match=r"rows must lie in \[0, 5\)"):
        rows.set_material(soft, rows=[5])


def test_a_flagged_job_reports_its_later_levels_and_frees_its_problem():
    """check stops job 2 where it presses harder than 2 N (its second level): that level carries the flag,
    the last reports the state there without iterations, and the next job still runs on that problem."""

    def too_hard(jobs, levels, part):
        hard = (jobs == 2) & (part.dof_force["grip"] > 2.0)
        return np.where(hard, fem.SolveStatus.ESCAPED, fem.SolveStatus.CONVERGED)

    got, _, starts = _stream(2, [3] * 5, check=too_hard)
    assert got[(2, 0)].converged[0] and not got[(2, 1)].converged[0]
    assert got[(2, 1)].status[0] == got[(2, 2)].status[0] == fem.SolveStatus.ESCAPED
    assert got[(2, 1)].newton_iterations[0] > 0 and got[(2, 2)].newton_iterations[0] == 0
    np.testing.assert_array_equal(got[(2, 2)].displacement, got[(2, 1)].displacement)
    assert all(got[(j, 2)].converged[0] for j in (0, 1, 3, 4))
    assert len(starts) == 5


def test_a_problem_flagged_by_its_start_reports_every_level_and_the_queue_goes_on():
    template = _solver()
    solver = _slots(2)
    got = {}

    def start(problems, jobs):
        solver.copy_state_from(template, rows=jobs, into=problems)
        solver.status[problems[jobs == 1]] = fem.SolveStatus.ESCAPED

    def on_levels(jobs, levels, part):
        for i, (j, k) in enumerate(zip(jobs.tolist(), levels.tolist())):
            got[(j, k)] = _row(part, i)

    solver.solve_stream([_levels(j) for j in range(4)], start, on_levels)
    assert sorted(got) == [(j, k) for j in range(4) for k in range(STEPS)]
    assert all(got[(1, k)].status[0] == fem.SolveStatus.ESCAPED for k in range(STEPS))
    assert all(got[(1, k)].newton_iterations[0] == 0 for k in range(STEPS))
    assert all(got[(j, STEPS - 1)].converged[0] for j in (0, 2, 3))


def _moved_pads(solver: fem.QuasiStaticSolver, job: int, lift: float, angle: float) -> dict:
    """Poses of grasp ``job``'s pads lifted by ``lift`` [m] along z and turned by ``angle`` [rad] about the
    grip axis y (through the box centre): the held box is dragged along (shear, twist)."""
    c, s = np.cos(angle), np.sin(angle)
    motion = np.eye(4)
    motion[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    motion[2, 3] = lift
    return {name: motion @ solver._poses[job, solver._body(name)] for name in ("left", "right")}


def _stream_through_two(template: fem.QuasiStaticSolver, jobs: list, final_state):
    """Stream ``jobs`` through two problems, job j starting from the template's problem j. Returns the
    solver, {(job, level): equilibrium}, {job: final_state(solver, problem)} taken when the job reached its
    last level (its problem still holds it), and the start and on_levels functions used."""
    solver = _slots(2)
    got, final, holder = {}, {}, {}

    def start(problems, job_ids):
        solver.copy_state_from(template, rows=job_ids, into=problems)
        holder.update(zip(job_ids.tolist(), problems.tolist()))

    def on_levels(job_ids, levels, part):
        for i, (j, k) in enumerate(zip(job_ids.tolist(), levels.tolist())):
            got[(j, k)] = _row(part, i)
            if k == len(jobs[j]) - 1:
                final[j] = final_state(solver, holder[j])

    solver.solve_stream(jobs, start, on_levels)
    return solver, got, final, start, on_levels


def test_jobs_that_move_bodies_stream_as_solves_with_body_poses():
    """Levels with "body_poses" drag the contacts as solve(body_poses=...) does: five jobs (grip harder,
    lift the pads, lift and twist them) through two problems reach the equilibria of one batch solving
    the levels with solve(), bit for bit, and every pad ends at the pose its job asked for."""
    template = _solver()
    moves = [(0.0, 0.0), (0.001, 0.0), (0.0015, 0.05)]  # (lift [m], twist [rad]) per level

    def poses(level):  # (B, 4, 4) per pad: every job's pose at this level
        return {
            name: np.stack([_moved_pads(template, j, *moves[level])[name] for j in range(5)])
            for name in ("left", "right")
        }

    expected = _solver()
    want = [
        expected.solve(targets={"grip": FORCES}),
        expected.solve(body_poses=poses(1)),
        expected.solve(targets={"grip": 1.2 * FORCES}, body_poses=poses(2)),
    ]
    jobs = [
        [
            {"grip": float(FORCES[j])},
            {"body_poses": _moved_pads(template, j, *moves[1])},
            {"grip": float(1.2 * FORCES[j]), "body_poses": _moved_pads(template, j, *moves[2])},
        ]
        for j in range(5)
    ]
    solver, got, final, start, on_levels = _stream_through_two(
        template, jobs, lambda solver, b: solver._poses[b].copy()
    )
    for j in range(5):
        for k in range(3):
            _assert_same(_row(want[k], j), got[(j, k)])
        assert got[(j, 2)].converged[0]
        np.testing.assert_array_equal(final[j], expected._poses[j])
        np.testing.assert_allclose(final[j][0], jobs[j][2]["body_poses"]["left"], atol=1e-15)
    # the box went up with the pads: its mean lift is the pads' (1.5 mm) within a tenth
    lift = got[(0, 2)].displacement[0][:, 2].mean() - got[(0, 0)].displacement[0][:, 2].mean()
    assert lift == pytest.approx(0.0015, rel=0.1)
    with pytest.raises(KeyError, match="no rigid body named 'thumb'"):
        solver.solve_stream([[{"body_poses": {"thumb": np.eye(4)}}]], start, on_levels)
    with pytest.raises(ValueError, match="pose of body 'left' in level 0 of job 0 must be 4x4"):
        solver.solve_stream([[{"body_poses": {"left": np.eye(3)}}]], start, on_levels)


def test_jobs_that_set_body_loads_stream_as_solves_with_body_load():
    """Levels with "body_load" load the object as solve(body_load=...) does: five jobs (grip harder, then
    a linear and an angular acceleration of the holding frame, each job its own direction) through two
    problems reach the equilibria of one batch solving the levels with solve(), bit for bit; a level
    without the key keeps the load before it, and each problem ends with its job's last load."""
    gravity = (0.0, 0.0, -9.81)
    accel = np.array([[3.0, 0.0, 1.0], [0.0, 4.0, 0.0], [-2.0, 1.0, 0.0], [1.0, 1.0, 1.0], [0.0, 0.0, 5.0]])
    spin = np.array(
        [[0.0, 0.0, 60.0], [40.0, 0.0, 0.0], [0.0, 50.0, 0.0], [30.0, 30.0, 0.0], [0.0, -40.0, 20.0]]
    )
    center = (0.0, 0.0, 0.01)
    linear = [fem.BodyLoad(gravity=gravity, linear_acceleration=a) for a in accel]
    angular = [fem.BodyLoad(gravity=gravity, angular_acceleration=w, rotation_center=center) for w in spin]
    expected = _solver()
    want = [
        expected.solve(targets={"grip": FORCES}),
        expected.solve(body_load=fem.BodyLoad(gravity=gravity, linear_acceleration=accel)),
        expected.solve(targets={"grip": 1.2 * FORCES}),
        expected.solve(
            body_load=fem.BodyLoad(gravity=gravity, angular_acceleration=spin, rotation_center=center)
        ),
    ]
    jobs = [
        [
            {"grip": float(FORCES[j])},
            {"body_load": linear[j]},
            {"grip": float(1.2 * FORCES[j])},
            {"body_load": angular[j]},
        ]
        for j in range(5)
    ]
    solver, got, final, start, on_levels = _stream_through_two(
        _solver(), jobs, lambda solver, b: {name: v[b].copy() for name, v in solver._load.arrays(2).items()}
    )
    for j in range(5):
        for k in range(4):
            _assert_same(_row(want[k], j), got[(j, k)])
        assert got[(j, 3)].converged[0]
        np.testing.assert_array_equal(final[j]["angular_acceleration"], spin[j])
        np.testing.assert_array_equal(final[j]["linear_acceleration"], 0.0)
    # the accelerations moved the box: the held box lags the frame's acceleration (d'Alembert load -m a)
    shift = got[(0, 1)].displacement[0].mean(axis=0) - got[(0, 0)].displacement[0].mean(axis=0)
    assert shift[0] < 0 and abs(shift[0]) > abs(shift[1])
    with pytest.raises(TypeError, match="body_load of level 0 of job 0 must be a BodyLoad"):
        solver.solve_stream([[{"body_load": (0.0, 0.0, 1.0)}]], start, on_levels)
    with pytest.raises(ValueError):
        solver.solve_stream([[{"body_load": fem.BodyLoad(gravity=np.zeros((2, 3)))}]], start, on_levels)


def test_jobs_are_checked():
    solver = _slots(2)

    def run(jobs):
        solver.solve_stream(jobs, lambda p, j: None, lambda j, k, part: None)

    with pytest.raises(ValueError, match="job 1 must be a non-empty sequence"):
        run([_levels(0), []])
    with pytest.raises(TypeError, match="level 0 of job 0 must be a dict"):
        run([[1.0]])
    with pytest.raises(KeyError, match="unknown dof 'grasp'"):
        run([[{"grasp": 1.0}]])
    with pytest.raises(ValueError, match="'grip' of level 1 of job 0 must be a finite scalar"):
        run([[{"grip": 1.0}, {"grip": np.nan}]])


def test_a_row_wise_state_copy_leaves_the_other_problems_untouched():
    """copy_state_from(into=...): the copied problem solves as its source, the others as if untouched."""
    source = _solver()
    reference = _solver()
    solver = _solver()
    solver.copy_state_from(source, rows=[4], into=[1])
    more = {"grip": FORCES}
    a, b, c = reference.solve(targets=more), solver.solve(targets=more), source.solve(targets=more)
    keep = [0, 2, 3, 4]
    _assert_same(a.take(np.array(keep)), b.take(np.array(keep)))
    # problem 1 now holds grasp 4 (its pose and state): as after a whole-batch copy
    whole = _solver()
    whole.copy_state_from(_solver(), rows=[0, 4, 2, 3, 4])
    _assert_same(whole.solve(targets=more).take(np.array([1])), b.take(np.array([1])))
    c4 = _solver().copy_state_from
    with pytest.raises(ValueError, match="into names 2 problems for 1 rows"):
        c4(source, rows=[0], into=[0, 1])
    with pytest.raises(ValueError, match="into must name distinct"):
        c4(source, rows=[0, 1], into=[1, 1])
    with pytest.raises(ValueError, match=r"into must lie in \[0, 5\)"):
        c4(source, rows=[0], into=[5])
    assert c.converged.all()


def test_a_row_wise_body_pose_moves_only_those_problems():
    """set_body_pose(rows=...) equals setting every problem's pose with the others' poses unchanged."""
    poses = {}
    for name, s in (("left", 1), ("right", -1)):
        T = np.tile(np.eye(4), (5, 1, 1))
        T[:, 1, 3] = s * (0.0075 + 0.004)
        T[:, 0, 3] = OFFSETS
        poses[name] = T
    whole, rows = _solver(), _solver()
    for name, T in poses.items():
        moved = T.copy()
        moved[[1, 3], 0, 3] = [0.003, -0.002]
        whole.set_body_pose(name, moved)
        rows.set_body_pose(name, moved[[1, 3]], rows=[1, 3])
    more = {"grip": FORCES}
    a, b, c = whole.solve(targets=more), rows.solve(targets=more), _solver().solve(targets=more)
    _assert_same(a.take(np.array([1, 3])), b.take(np.array([1, 3])))
    _assert_same(c.take(np.array([0, 2, 4])), b.take(np.array([0, 2, 4])))  # the others as never moved
    with pytest.raises(ValueError, match=r"rows must lie in \[0, 5\)"):
        rows.set_body_pose("left", np.eye(4), rows=[7])


def test_the_damping_shift_rewrites_only_the_problems_whose_damping_changed():
    """The Levenberg-Marquardt diagonal shift on the device equals regularization + springs + damping x
    unit for every problem after any sequence of damping changes, spring switches, row-wise materials and
    row-wise state copies, while each update writes only the problems whose damping changed."""
    solver, source = _solver(), _solver()
    written = []
    put_rows = solver._put_rows
    solver._put_rows = lambda array, per, rows, values=0.0: (
        written.append(sorted(np.asarray(rows).tolist())) if array is solver._diag_shift else None,
        put_rows(array, per, rows, values),
    )

    def expect(damping):
        shift = solver._diag_shift_base + np.asarray(damping)[:, None, None] * solver._damping_scale
        device = solver._diag_shift.numpy().reshape(5, solver.rows_per_problem, 3)
        np.testing.assert_array_equal(device, shift)

    steps = [
        ([0.0, 1e-3, 0.0, 0.0, 0.0], [1]),
        ([0.0, 1e-3, 0.0, 2e-3, 0.0], [3]),
        ([0.0, 3e-4, 0.0, 2e-3, 5e-3], [1, 4]),
    ]
    for damping, rows in steps:
        written.clear()
        solver._set_damping_shift(np.array(damping))
        assert written == [rows]
        expect(damping)
    # the springs switch writes every problem's shift without damping: the next update writes the damped
    solver._stabilize(np.array([True, False, True, False, True]))
    expect(np.zeros(5))
    damping = np.array([0.0, 3e-4, 0.0, 2e-3, 5e-3])
    written.clear()
    solver._set_damping_shift(damping)
    assert written == [[1, 3, 4]]
    expect(damping)
    # a row-wise material drops those rows' damping; a row-wise copy takes the source's
    solver.set_material(fem.Material(4e4, 0.35, 1000.0), rows=[3])
    damping[3] = 0.0
    expect(damping)
    source._set_damping_shift(np.array([7e-4, 0.0, 0.0, 0.0, 0.0]))
    solver.copy_state_from(source, rows=[0], into=[4])
    damping[4] = 7e-4
    expect(damping)
    written.clear()
    solver._set_damping_shift(damping)  # nothing changed: nothing written
    assert written == []
