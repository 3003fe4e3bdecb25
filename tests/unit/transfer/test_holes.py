"""The hole search a step per command (transfer/holes.py): no command pays a whole search, the fills still come."""

from __future__ import annotations

import numpy as np

from transfer.holes import hole_search, run_search
from transfer.policy import make_policy
from transfer.store import PairStore


def _top_speed_store():
    """The paper's cubic learner after a mission that drove only at its top speed and turned on the spot at its
    lowest: the map between is a guess, with holes on a fast curve's way."""
    from sim_learner.experiments import mpc_case

    case = mpc_case(False)
    store = PairStore(case.learner_bounds, case.teacher_bounds, k_min=5)
    lb = case.learner_bounds
    for n in [(1.0, (j + 0.5) / 11) for j in range(11)] + [(0.0, 0.0), (0.0, 1.0)]:
        u = lb.denormalise(np.array(n))
        for _ in range(store.k_min):
            store.add(case.learner.response(u), u)
    return case, store


def _count_maps(p) -> list[int]:
    """Count the policy's unperturbed maps (a one-element list the test resets and reads)."""
    maps = [0]
    inner = p._unperturbed

    def counted(*a):
        maps[0] += 1
        return inner(*a)

    p._unperturbed = counted
    return maps


def test_a_command_pays_at_most_one_step_of_a_hole_search_and_the_burst_follows_its_last_step() -> None:
    case, store = _top_speed_store()
    t = np.array([case.true_box.v[1], 0.12])  # a left curve at the learned top speed
    p = make_policy(store, "scm", seed=0)
    maps = _count_maps(p)
    per_command, methods, builds = [], [], []
    for _ in range(400):
        maps[0], b0 = 0, p.mapper.builds
        m = p.map(t)
        per_command.append(maps[0])
        builds.append(p.mapper.builds - b0)
        methods.append(m.method)
        store.add(case.learner.response(m.u_L), m.u_L)
    assert p.searches >= 3 and methods.count("perturb") >= 3 * store.k_min  # the fills came all the same
    # the command's own map and at most one SC map of a search: a whole search maps up to 2 * FILL_CHECKS more
    assert max(per_command) <= 2, max(per_command)
    # and at most one SC map built per command: its own region's, or else one for the search
    assert max(builds) <= 1 and sum(builds) >= 3, (max(builds), sum(builds))
    # a burst begins on the command after the search's last step: the command before a burst's first fill served
    # the teacher's command unperturbed
    first = [k for k in range(1, len(methods)) if methods[k] == "perturb" and methods[k - 1] != "perturb"]
    assert first and all(methods[k - 1] != "perturb" for k in first)


def test_a_search_run_at_once_finds_what_its_steps_find() -> None:
    """The same search, stepped or run at once, names the same hole and command (on an unchanged store)."""
    case, store = _top_speed_store()
    t = np.array([case.true_box.v[1], 0.12])
    p = make_policy(store, "scm", seed=0)
    search, steps = hole_search(p, t), 0
    while True:
        try:
            next(search)
            steps += 1
        except StopIteration as done:
            stepped = done.value
            break
    at_once = run_search(hole_search(p, t))
    assert steps >= 2 and stepped is not None and at_once is not None
    assert stepped[0] == at_once[0]
    np.testing.assert_allclose(stepped[1], at_once[1])


def test_prepare_builds_the_sc_map_a_map_needs_and_the_map_then_builds_nothing() -> None:
    from transfer.mappers import ScmMapper

    _, store = _top_speed_store()
    mapped = 0
    for t_n in np.stack(np.meshgrid(np.linspace(0.05, 0.95, 7), np.linspace(0.05, 0.95, 7)), -1).reshape(-1, 2):
        alone = ScmMapper(store).map_normalised(t_n)
        m = ScmMapper(store)
        built = m.prepare(t_n)
        assert not m.prepare(t_n)  # built already (or no region: nothing to build)
        before = (m.builds, len(m._quads))
        got = m.map_normalised(t_n)
        assert (got is None) == (alone is None)
        if got is not None and alone is not None:
            assert built and (m.builds, len(m._quads)) == before  # the map built nothing more
            np.testing.assert_array_equal(got[0], alone[0])
            assert got[1] == alone[1]
            mapped += 1
    assert mapped >= 3


def test_a_deferred_search_leaves_every_command_its_own_map_and_its_burst_comes_one_command_later() -> None:
    """``defer_search``: a command only asks for its search's step, which ``search_step`` runs after it; the
    commands are the inline policy's until a burst, which begins one command later."""
    import copy

    case, store = _top_speed_store()
    t = np.array([case.true_box.v[1], 0.12])
    inline, deferred = make_policy(store, "scm", seed=0), make_policy(copy.deepcopy(store), "scm", seed=0)
    deferred.defer_search = True
    maps = _count_maps(deferred)
    a, b, steps, in_steps = [], [], 0, 0
    for _ in range(400):
        maps[0] = 0
        m = deferred.map(t)
        assert maps[0] <= (2 if m.method == "perturb" else 1)  # its own map (a burst's yaw rate's), no search's
        b.append(m)
        deferred.store.add(case.learner.response(m.u_L), m.u_L)
        maps[0] = 0
        steps += deferred.search_step()
        in_steps += maps[0]
        assert not deferred.search_step()  # one step per command that asked for one
        m = inline.map(t)
        a.append(m)
        inline.store.add(case.learner.response(m.u_L), m.u_L)
    assert deferred.searches >= 3 and steps >= 3 and in_steps > 0  # the search's maps were the steps'
    assert [m.method for m in b].count("perturb") >= 3 * store.k_min  # the fills came all the same
    k = next(k for k in range(len(a)) if a[k].method != b[k].method or not np.array_equal(a[k].u_L, b[k].u_L))
    assert a[k].method == "perturb" and b[k].method != "perturb"  # the inline burst's first command
    assert b[k + 1].method == "perturb"  # the deferred one's, a command later
    np.testing.assert_array_equal(a[k].u_L, b[k + 1].u_L)  # at the hole the same search named
