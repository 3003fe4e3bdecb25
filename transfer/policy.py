"""The transfer policy: teacher command -> learner command, and how it was obtained (paper Section 5.2).

Two policies implement one :class:`Policy` protocol, ``map(u_T, *, plan=None, explore=True) -> Mapped`` with
:class:`Mapped` ``(u_L, method, region)``: :class:`PaperPolicy` and :class:`GuidedPolicy` (``make_policy(store,
mapper, exploration=...)`` builds one by name). They decide differently what happens where no mapping region holds
u_T; both map through the region the same way where one does, and both share one unperturbed mapping for
``explore=False``. The result is always finite and inside the learner's hard bounds; a non-finite u_T is refused
with ValueError. With the ``identity`` mapper (the paper's baseline) every command is ``"direct"``, clipped.

:class:`PaperPolicy`: the paper's algorithm as published (``plan`` is ignored). ``method`` is

- ``"scm"`` (or the alternative mapper's name): a mapping region holds u_T; or u_T lies inside the learned
  limits but just outside the triangulated region (within ``saturate``, normalised units, default 0.1 ~ one grid
  cell), as a saturated controller's commands at the edge of the limits do: then the nearest point of the
  learned region is mapped (otherwise such commands would be perturbed forever, since the refined pairs of the
  outermost cells are cell means and lie inside the limits);
- ``"direct"``: no region, and the learner cell of u_T (u_T read as a learner command, clipped into the learner's
  box) holds no refined pair yet: apply the teacher command as it is, clipped (explore; the pair it creates fills
  that cell);
- ``"perturb"`` (exploration): u_T sits at a learned limit whose learner boundary has never been driven: the
  learner's extreme command on that axis is sent once so the limit is measured, not extrapolated (the *probe*); or
  no region, but the cell of u_T is already configured: sample a command uniformly inside the nearest
  unconfigured cell around it (ring by ring; in the ring, the cell nearest to where the least-squares affine
  fit of the refined pairs puts u_T; ties broken by the policy's random generator) so that pairs are
  learned where they are missing. With every cell configured it falls back to ``"direct"``.

:class:`GuidedPolicy` (the default): exploration should cost the mission as little as possible. Every command
is the policy's best estimate of the learner command for u_T, or, when it explores, the point of the chosen
unconfigured cell nearest to that estimate. ``method`` is

- ``"scm"`` (or the alternative mapper's name): a mapping region holds u_T (no saturation: see ``"direct"``) and,
  with ``choice`` (``[transfer] map_choice``), :class:`transfer.choice.MapChoice` chose the SC map for it (else
  ``"barycentric"``);
- ``"barycentric"``: with the ``scm`` (or ``affine``) mapper, u_T lies in a Delaunay triangle of the refined pairs
  but the mapper has no usable region there (no neighbour forms a simple counter-clockwise quadrilateral on both
  sides: the slivers along a row of boundary-cell means): linear interpolation on that triangle, instead of
  exploring around a command the learned pairs already enclose; and a command at a learned limit whose boundary
  has been driven (within ``ALONG_LIMIT_TOL``, as a bounded MPC's saturated commands are): the learner's extreme
  on that axis and, on the other, linear interpolation between the two neighbouring refined pairs of the boundary
  row of cells (those pairs are nearly collinear in the teacher domain, so the 2-D regions there are slivers; with
  the store's ``adapt``, beyond the row's pairs the region's map); this holds for every policy's unperturbed mapping;
- ``"direct"``: no region holds u_T, and the teacher command is applied directly *relative to the learned region*:
  the estimate is the linear interpolation of the region's nearest point ``q`` (on a hull edge, between that
  edge's two pairs) plus the offset ``u_T - q`` taken one-to-one in physical units, clipped into the learner's
  box; ``region`` holds the pair ids of the triangle ``q`` lies on. Before there is a triangulated region (fewer
  than three refined pairs, or all collinear) it is the paper's ``"direct"``, the teacher command itself,
  clipped, with an empty ``region``. It joins the region's map continuously at the region's edge, so a saturated
  controller's commands just outside the region of cell means are served without exploring (where the paper
  maps the nearest point and drops the offset). Sent when ``u_T`` is within ``saturate`` (normalised teacher
  units) of the region, when the estimate's learner cell holds no refined pair yet (the pair it creates fills that
  cell), when ``explore`` is False, or when no cell next to it is left to explore;
- ``"perturb"`` (only when ``explore`` is True): the probe of a never-driven limit, as in the paper but with the
  other axis at the estimate rather than at the raw teacher command; or u_T is more than ``saturate`` outside the
  region and the estimate's cell is configured: among the unconfigured cells adjacent to it (ring 1 only), the
  one with the least ``d(estimate, cell) + d(plan, cell)`` is chosen, where ``d`` is the distance (normalised
  learner units) to the cell's rectangle and ``d(plan, cell)`` the least distance of the estimates of the teacher's
  next planned commands ``plan`` (0 without a plan); ties broken by the random generator (the only use of it). The
  command sent is the point of that cell nearest to the estimate, moved ``inset`` (fraction of a cell) inside it,
  not a uniform sample: the pair lands where it is missing at the least detour from what the mission needs;
  or a *fill* (below).

*Filling the map's holes* (guided, ``fill_budget``, default ``FILL_BUDGET``). A mission that drives at its limits
(an MPC at the learned top speed and yaw rates) never asks for the commands in between, so without it the map there
is a straight line across the unconfigured cells (for the paper's cubic learner: learner speeds 0.1-0.9 of the
range, whose responses span three quarters of the teacher's speeds). A fill explores such a hole on the teacher's
own path, only slower: for a command served from the learned region, the policy considers the teacher command slowed
by s (1 down to ``fill_depth``, and no slower than the learned speed limit) at the same curvature, mapped: the
learner speed the map gives for ``s * v_T`` and the yaw rate it gives for ``s * omega_T`` at ``v_T`` (where the
mission drives, so that row is learned; exact when the learner's yaw-rate response does not depend on its speed; no
fill where that yaw rate has no learned region). Among the candidates in unconfigured cells it fills a cell an
earlier burst began, else the one whose teacher command is farthest from every refined pair (the map's biggest hole
on the teacher's way); the candidates are ranked on the piecewise-linear map of the same triangles (no SC map is
built for a guess) and the best ``FILL_CHECKS`` of them mapped with the SC map itself. A burst sends k_min commands
into that cell, each at the learner speed of the cell's pairs so far and at the yaw rate that gives the teacher's
curvature at the speed those pairs measured (only the first command of a burst relies on the map's guess of the
hole's speed); the command stays in the burst's cell while that yaw rate is within one cell of it (moved into it: a
cell is finished at a yaw-rate error of at most one cell), else the burst moves to that yaw rate's cell if it is
unconfigured, and ends otherwise (or with no learned yaw rate). Fills are paid from a token budget: ``fill_budget``
per command served from the region, at most one cell's k_min saved, and a burst starts only with k_min saved
(``fill_phase`` of it saved from the start: a station's robots each start at their own, so that a fleet started
together does not search in one tick); a search for a hole that found none makes the next wait as many commands as
it cost maps (a learned store with no hole on the teacher's way is a station's steady state: its commands must not
pay a search each), and a store with no unconfigured cell is never searched. A search runs a short step per
command (:mod:`transfer.holes`: the ranking, then each map of each check), the commands meanwhile served as
without it, and its burst begins at the command after its last step, if its cell is still a hole: no command
pays a whole search. With ``defer_search`` (a station's) a command only asks for its step, which the caller runs
after it (:meth:`GuidedPolicy.search_step`): no command pays any of it, and the burst begins one command later.
Fills cost time, not path: the robot slows down along the curve the teacher asked for. Like every perturbation
they never happen where ``explore`` is False (near obstacles).

``explore=False`` (the caller's choice, e.g. near obstacles: :class:`transfer.step.TransferStep` decides it) means
no perturbation of any kind, for both policies: the command is the guided policy's region map (with its barycentric
fallback) or its estimate; the paper's algorithm has no such mode, so it shares the guided one. ``plan`` is an
optional (K, 2) array of the teacher's next planned commands (teacher units, after u_T; :func:`planned_commands`
recovers them from an MPC's predicted states), or a function returning it, called only when a cell is chosen;
it only steers which cell is explored. The method names are those of the bridge's ``Command`` message.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from transfer.at_limit import ALONG_LIMIT_TOL, AT_LIMIT, LimitMap  # noqa: F401 (the policy's names for its callers)
from transfer.choice import MapChoice
from transfer.domain import clamp
from transfer.holes import FILL_CHECKS, Hole, Search, hole_search, run_search  # noqa: F401 (FILL_CHECKS: the policy's)
from transfer.mappers import AffineMapper, BarycentricMapper, IdentityMapper, Mapper, Region, ScmMapper, make_mapper
from transfer.pairs import planned_commands  # noqa: F401 (the policy's helper for its callers)
from transfer.store import PairStore

EXPLORATIONS = ("paper", "guided")
#: the guided policy's default share of region-served commands that may fill holes of the map (module docstring)
FILL_BUDGET = 0.08
#: at which learner speed the probe of a never-driven yaw-rate limit is sent: ``at-command`` (the default, the
#: paper's: at the speed the command maps to, the learner's slowest while nothing is learned) or ``at-top-speed``
#: (opt-in: the learner's top speed). A learner that cannot turn in place (an Ackermann rover, docs/BENCHMARKS.md
#: "The transfer on SITL") probed at its slowest speed barely turns, and the learned box then allows almost no turn
#: at *any* speed, so the teacher never asks for the faster turning commands that would teach it otherwise; probed
#: at its top speed it shows the turn rate it has when it drives (and the box then allows that rate at every speed:
#: a box cannot say that turning needs speed either way)
TURN_PROBES = ("at-command", "at-top-speed")


@dataclass(frozen=True)
class Mapped:
    """A learner command (learner units), the method that produced it and the refined-pair ids of its region;
    ``vetoed``: exploration was not allowed for it (set by :class:`transfer.step.TransferStep`)."""

    u_L: NDArray[np.float64]
    method: str
    region: tuple[int, ...] = ()
    vetoed: bool = False


#: the teacher's next planned commands ``(K, 2)``, or a function that returns them (read only when needed), or None
Plan = ArrayLike | Callable[[], ArrayLike] | None


class Policy(Protocol):
    """Teacher command -> learner command over a pair store (module docstring)."""

    store: PairStore
    mapper: Mapper
    rng: np.random.Generator

    def map(self, u_T: ArrayLike, *, plan: Plan = None, explore: bool = True) -> Mapped:
        """The learner command for ``u_T``; ``plan``: the teacher's next commands (a hint); ``explore``: whether
        it may perturb."""
        ...


class _PolicyBase:
    """What both policies share: the checks, the identity baseline, the probe of a never-driven limit and the
    unperturbed mapping (region, barycentric fallback, estimate relative to the learned region)."""

    def __init__(self, store: PairStore, mapper: str | Mapper = "scm", rng: np.random.Generator | None = None,
                 *, seed: int | None = None, saturate: float = 0.1, probe_tol: float = 1e-6,
                 inset: float = 0.1, turn_probe: str = "at-command", choice: bool = False,
                 at_limit: str = "row") -> None:
        """``mapper``: a mapper name (``scm``, ``barycentric``, ``affine``, ``identity``) or object; ``rng`` (or
        ``seed``): the random generator of the exploration; ``saturate``: normalised teacher distance to the
        learned region below which commands are served from the region instead of explored; ``probe_tol``: how
        close to a never-driven learned limit a command must be to probe it; ``inset``: how far (fraction of a
        cell) inside the chosen cell a guided perturbation lands; ``turn_probe``: at which learner speed the probe
        of a never-driven yaw-rate limit is sent (:data:`TURN_PROBES`); ``choice``: with the ``scm`` mapper, each
        command inside the learned region is mapped by the SC map or linear interpolation as
        :class:`transfer.choice.MapChoice` decides (False: the paper's SC map wherever it has a region); ``at_limit``:
        how a command at a driven limit is mapped (:data:`AT_LIMIT`)."""
        self.at_limit = at_limit
        if not 0.0 <= inset < 0.5:
            raise ValueError(f"inset must be in [0, 0.5), got {inset}")
        if turn_probe not in TURN_PROBES:
            raise ValueError(f"unknown turn_probe {turn_probe!r}; known: {', '.join(TURN_PROBES)}")
        self.turn_probe, self.store = turn_probe, store
        self.saturate, self.probe_tol, self.inset = float(saturate), float(probe_tol), float(inset)
        self.mapper: Mapper = make_mapper(mapper, store) if isinstance(mapper, str) else mapper
        identity = isinstance(self.mapper, IdentityMapper)
        self._affine = None if identity else AffineMapper(store)
        # a triangle of refined pairs where the mapper has no usable region is interpolated linearly
        self._fallback = (BarycentricMapper(store)
                          if not identity and not isinstance(self.mapper, BarycentricMapper) else None)
        if isinstance(self.mapper, ScmMapper):  # one Delaunay triangulation a store revision for the three of them
            for linear in (self._fallback, self._affine):
                if linear is not None:
                    linear.twin = self.mapper
        self._choice = MapChoice(self.mapper) if choice and isinstance(self.mapper, ScmMapper) else None
        self.rng = rng if rng is not None else np.random.default_rng(seed)
        self._limits = LimitMap(store, at_limit, self._region_map, self._beyond_row)

    def map(self, u_T: ArrayLike, *, plan: Plan = None, explore: bool = True) -> Mapped:
        """The learner command for teacher command ``u_T`` (see the module docstring for every case)."""
        t = np.asarray(u_T, dtype=float).reshape(2)
        if not all(map(math.isfinite, t.tolist())):
            raise ValueError(f"teacher command must be finite, got {t}")
        if isinstance(self.mapper, IdentityMapper):
            return Mapped(self.store.learner_bounds.clip(t), "direct")
        t_n = self.store.teacher_bounds.normalise(t)
        if not explore:
            u, method, ids, _ = self._unperturbed(t, t_n)
            return Mapped(u, method, ids)
        return self._explore(t, t_n, plan)

    def _explore(self, t: NDArray[np.float64], t_n: NDArray[np.float64], plan: Plan) -> Mapped:
        raise NotImplementedError

    # ------------------------------------------------------------------------------------------ shared helpers
    def _unperturbed(self, t: NDArray[np.float64], t_n: NDArray[np.float64]) -> tuple[NDArray[np.float64], str,
                                                                                      Region, float]:
        """The best unperturbed learner command: (learner units, method, region, gap to the learned region)."""
        lb = self.store.learner_bounds
        region = self._along_limit(t_n) or self._map_chain(t_n)
        if region is not None:  # beyond a limit's row (``adapt``): the gap of the other axis' estimate, if any
            (l_n, method, ids), gap = region[:3], (region[3] if len(region) > 3 else 0.0)
        else:
            l_n, method, ids, gap = self._estimate(t, t_n)
        return lb.clip(lb.denormalise(l_n)), method, ids, gap

    def _along_limit(self, t_n: NDArray[np.float64], linear: bool = False) -> tuple | None:
        """A command at a driven learned limit, mapped (:meth:`transfer.at_limit.LimitMap.map`), or None."""
        return self._limits.map(t_n, linear)

    def _region_map(self, t_n: NDArray[np.float64]) -> tuple | None:
        """The mapper's region (with ``choice``, the chosen map) at ``t_n``: (l_n, method, region) or None."""
        if self._choice is not None:
            return self._choice.map_normalised(t_n)
        res = self.mapper.map_normalised(t_n)
        return None if res is None else (res[0], self.mapper.name, res[1])

    def _beyond_row(self, t_n: NDArray[np.float64]) -> tuple:
        """The unperturbed chain for a command at a limit but beyond its row's pairs (``adapt``)."""
        return self._map_chain(t_n) or self._estimate(self.store.teacher_bounds.denormalise(t_n), t_n)

    def _unperturbed_many(self, ts: NDArray[np.float64], *, linear: bool = False) -> tuple[NDArray[np.float64],
                                                                                           list[str]]:
        """:meth:`_unperturbed` of every row of ``ts`` ``(n, 2)`` (teacher units): the learner commands ``(n, 2)``
        and the methods, the same as one call per row; the mapper locates and maps the rows not at a learned limit
        together (:meth:`transfer.mappers.Mapper.map_many`). ``linear``: the piecewise-linear map on the same
        triangles instead of the mapper (no SC map is built: a guess that ranks a hole search's candidates; it
        has a region exactly where the mapper's chain has one, so "direct" means the same)."""
        tb, lb = self.store.teacher_bounds, self.store.learner_bounds
        ts_n = tb.normalise(ts)
        out = np.empty_like(ts_n)
        methods = [""] * len(ts_n)
        rest: list[int] = []
        for i in range(len(ts_n)):
            along = self._along_limit(ts_n[i], linear)
            if along is not None:
                out[i], methods[i] = along[0], along[1]
            else:
                rest.append(i)
        chain = (self._fallback or self.mapper,) if linear else (self._choice or self.mapper, self._fallback)
        for mapper in chain:
            if not rest or mapper is None:
                continue
            unmapped = []
            for i, got in zip(rest, mapper.map_many(ts_n[rest])):
                if got is not None and np.all(np.isfinite(got[0])):  # a MapChoice names its method
                    out[i], methods[i] = got[0], got[1] if len(got) == 3 else mapper.name  # type: ignore[union-attr]
                else:
                    unmapped.append(i)
            rest = unmapped
        for i in rest:
            out[i], methods[i], _, _ = self._estimate(ts[i], ts_n[i])
        return lb.clip(lb.denormalise(out)), methods

    def _probe_limits(self, t_n: NDArray[np.float64], base: NDArray[np.float64]) -> NDArray[np.float64] | None:
        """A teacher command saturated at a learned limit whose learner boundary has never been seen: send the
        learner's extreme command on that axis once (``base``, learner units, on the other), so the boundary pair
        fixes the limit (paper: a new outlier on the boundary moves the bound). Without it a proportional estimate
        from an interior outlier, which underestimates a convex learner response (the paper's h_v = v^3), would
        bound the teacher for good."""
        lim = self.store.limits
        lb = self.store.learner_bounds
        u = np.array(base, dtype=float)
        probed = [False, False]
        for a in range(2):
            if lim.bcnt_hi[a] == 0 and t_n[a] >= lim.hi[a] - self.probe_tol:
                u[a] = lb.hi[a]
                probed[a] = True
            elif lim.bcnt_lo[a] == 0 and t_n[a] <= lim.lo[a] + self.probe_tol:
                u[a] = lb.lo[a]
                probed[a] = True
        if probed[1] and self.turn_probe == "at-top-speed":
            u[0] = lb.hi[0]  # a learner whose turn rate grows with its speed turns most at its top speed
        return u if any(probed) else None

    def _map_chain(self, t_n: NDArray[np.float64]) -> tuple[NDArray[np.float64], str, Region] | None:
        """The mapper's region for t_n (with ``choice``: the SC map or linear, as chosen), else the barycentric
        interpolation of its triangle."""
        if self._choice is not None:
            got = self._choice.map_normalised(t_n)
            if got is not None:
                return got
        elif (res := self.mapper.map_normalised(t_n)) is not None and np.all(np.isfinite(res[0])):
            return res[0], self.mapper.name, res[1]
        if self._fallback is not None:
            res = self._fallback.map_normalised(t_n)
            if res is not None and np.all(np.isfinite(res[0])):
                return res[0], self._fallback.name, res[1]
        return None

    def _estimate(self, t: NDArray[np.float64], t_n: NDArray[np.float64]) -> tuple[NDArray[np.float64], str,
                                                                                  Region, float]:
        """The best guess outside the triangulated region: (normalised learner command, method, region, gap). It
        is the linear interpolation of the region's nearest point ``q`` (on a hull edge: between its two pairs)
        plus the offset ``t - q`` read one-to-one in physical units (the teacher command applied directly, relative
        to the learned region), and ``gap`` is ``|t - q|`` (normalised teacher units); before there is a region,
        the teacher command read as a learner command (gap infinite)."""
        lb, tb = self.store.learner_bounds, self.store.teacher_bounds
        linear = self._fallback if self._fallback is not None else self.mapper
        near = linear.nearest_on_hull(t_n)
        if near is not None:
            res = linear.map_normalised(near[0])
            if res is not None and np.all(np.isfinite(res[0])):
                offset = (t_n - near[0]) * tb.span / lb.span  # normalised teacher step -> normalised learner step
                return clamp(res[0] + offset, 0.0, 1.0), "direct", res[1], float(near[1])
        return lb.normalise(lb.clip(t)), "direct", (), float("inf")


class PaperPolicy(_PolicyBase):
    """The paper's exploration as published (module docstring); ``plan`` is ignored."""

    def _explore(self, t: NDArray[np.float64], t_n: NDArray[np.float64], plan: Plan) -> Mapped:
        lb = self.store.learner_bounds
        probe = self._probe_limits(t_n, lb.clip(t))
        if probe is not None:
            return Mapped(probe, "perturb")
        res = self.mapper.map_normalised(t_n)
        if res is None and self.saturate > 0 and self.store.limits.contains(t):
            # inside the learned limits but just outside the learned region: a command at the edge of what the
            # learner can do (a saturated controller) maps through the nearest learned command, not by exploring
            near = self.mapper.nearest_on_hull(t_n)
            if near is not None and near[1] <= self.saturate:
                res = self.mapper.map_normalised(near[0])
        if res is not None:
            l_n, region = res
            u = lb.clip(lb.denormalise(l_n))
            if np.all(np.isfinite(u)):
                return Mapped(u, self.mapper.name, region)
        direct = lb.clip(t)
        cell = self.store.cell_of(direct)
        if not self.store.is_configured(cell):
            return Mapped(direct, "direct")
        target = self._nearest_unconfigured(cell, self._predict(t_n, direct))
        if target is None:
            return Mapped(direct, "direct")
        gv, gw = self.store.grid
        n = (np.array(target, dtype=float) + self.rng.random(2)) / np.array([gv, gw], dtype=float)
        return Mapped(lb.clip(lb.denormalise(n)), "perturb")

    def _predict(self, t_n: NDArray[np.float64], direct: NDArray[np.float64]) -> NDArray[np.float64]:
        """Where the learner command for t_n probably is (normalised): the least-squares affine map of the refined
        pairs, or the teacher command itself while there are too few pairs for one."""
        guess = self._affine.extrapolate(t_n) if self._affine is not None else None
        if guess is None:
            return self.store.learner_bounds.normalise(direct)
        return clamp(guess, 0.0, 1.0)

    def _nearest_unconfigured(self, cell: tuple[int, int], towards: NDArray[np.float64]) -> tuple[int, int] | None:
        """The unconfigured cell of the nearest ring around ``cell`` closest to ``towards`` (normalised learner
        point; ties broken by the random generator): exploring where the command probably maps, not anywhere."""
        gv, gw = self.store.grid
        configured = self.store.configured()
        i0, j0 = cell
        goal = np.asarray(towards) * np.array([gv, gw], dtype=float)
        for r in range(1, max(gv, gw)):
            ring = [
                (i, j)
                for i in range(max(0, i0 - r), min(gv, i0 + r + 1))
                for j in range(max(0, j0 - r), min(gw, j0 + r + 1))
                if max(abs(i - i0), abs(j - j0)) == r and not configured[i, j]
            ]
            if ring:
                d = np.array([np.hypot(i + 0.5 - goal[0], j + 0.5 - goal[1]) for i, j in ring])
                best = np.flatnonzero(d <= d.min() + 1e-9)
                return ring[int(best[self.rng.integers(best.size)])]
        return None


class GuidedPolicy(_PolicyBase):
    """Exploration at the least detour from what the mission needs, steered by the teacher's plan (module
    docstring)."""

    def _explore(self, t: NDArray[np.float64], t_n: NDArray[np.float64], plan: Plan) -> Mapped:
        lb = self.store.learner_bounds
        u, method, ids, gap = self._unperturbed(t, t_n)
        probe = self._probe_limits(t_n, u)
        if probe is not None:
            return Mapped(probe, "perturb")
        if gap <= self.saturate:
            fill = self._fill(t)
            if fill is not None:
                return Mapped(fill, "perturb")
            return Mapped(u, method, ids)
        cell = self.store.cell_of(u)
        if not self.store.is_configured(cell):
            return Mapped(u, method, ids)
        target = self._guided_target(cell, lb.normalise(u), plan)
        if target is None:
            return Mapped(u, method, ids)
        return Mapped(lb.clip(lb.denormalise(self._nearest_in_cell(target, lb.normalise(u)))), "perturb")

    def __init__(self, store: PairStore, mapper: str | Mapper = "scm", rng: np.random.Generator | None = None,
                 *, fill_budget: float = FILL_BUDGET, fill_depth: float = 0.3, fill_phase: float = 0.0,
                 **options: float | str | None) -> None:
        """``fill_budget``: the share of the commands served from the learned region that may fill a hole of the
        map (0: never); ``fill_depth``: the slowest a fill asks for, as a fraction of the teacher's speed (what the
        learner then drives is the map's guess in the hole, which the fill measures); ``fill_phase`` (0 to 1): how
        much of the first burst's budget is saved up from the start (a station gives each robot its own, so that
        the robots of a fleet that start together do not all search for a hole in the same tick); the other
        options as :class:`_PolicyBase` takes them."""
        super().__init__(store, mapper, rng, **options)  # type: ignore[arg-type]
        if not 0.0 <= fill_budget < 1.0:
            raise ValueError(f"fill_budget must be in [0, 1), got {fill_budget}")
        if not 0.0 < fill_depth < 1.0:
            raise ValueError(f"fill_depth must be in (0, 1), got {fill_depth}")
        if not 0.0 <= fill_phase < 1.0:
            raise ValueError(f"fill_phase must be in [0, 1), got {fill_phase}")
        self.fill_budget = float(fill_budget)
        self.fill_depth = float(fill_depth)
        # earned at fill_budget per command served from the region, at most one cell's k_min
        self._fill_tokens = float(fill_phase) * store.k_min
        self._fill_cell: tuple[int, int] | None = None  # the hole the current burst fills; None between bursts
        self._speeds = np.linspace(1.0, self.fill_depth, 29)[1:]  # the slowed speeds s a hole search tries
        self._served = 0  # commands served from the region so far: the clock of the hole search
        #: no new hole search before this many served commands: a search that found no hole waits as many commands
        #: as it cost maps, so searching costs at most about one map per command however long no hole is found
        self._search_after = 0
        self._search: Search | None = None  # the hole search under way, a step per command (transfer/holes.py)
        self.searches = 0  # hole searches begun
        #: the search's step of a command runs after it, when its caller asks (:meth:`search_step`), instead of in
        #: the command's own mapping: a station's tick then sends its command without waiting for the step
        self.defer_search = False
        self._search_due = False  # a command asked for a step of the search that :meth:`search_step` has not run
        self._search_done: tuple[Hole] | None = None  # a deferred search's result, for the next command's fill

    def _fill(self, t: NDArray[np.float64]) -> NDArray[np.float64] | None:
        """The fill of a hole of the map (module docstring), or None: no budget, no hole, or a paused burst."""
        store = self.store
        if self.fill_budget <= 0.0 or not t[0] > 0.0:
            return None
        self._served += 1
        self._fill_tokens = min(self._fill_tokens + self.fill_budget, float(store.k_min))
        c = self._fill_cell
        if c is not None and (store.is_configured(c) or self._fill_tokens < 1.0):
            c = self._fill_cell = None  # the burst is over: its hole is configured, or its budget spent
        if c is not None and store.cells.count[c] > 0:
            # the burst goes on at the learner speed of its pairs so far, turning for the teacher's curvature at the
            # speed those pairs measured (in its cell, or in that yaw rate's own cell: _in_burst)
            mean_T, mean_L = store.cluster_mean(c)
            v_bar = float(store.teacher_bounds.denormalise(mean_T)[0])
            u = self._at_speed(t, float(mean_L[0]), v_bar / float(t[0]))
            u = None if u is None else self._in_burst(c, u)
            if u is None:  # no learned yaw rate for it, or only known cells there: the burst ends
                self._fill_cell = None
                return None
            self._fill_cell = store.cell_of(u)
            self._fill_tokens -= 1.0
            return u
        if self._fill_tokens < store.k_min:  # a new burst starts with one whole cell's budget
            return None
        if self._search_done is not None:  # a deferred search ended after the command before
            (hole,), self._search_done = self._search_done, None
        else:
            if self._search is None:
                if self._served < self._search_after or store.n_configured() == store.cells.count.size:
                    return None  # a search found no hole lately, or the store has none left
                self._search = hole_search(self, t)
                self.searches += 1
            if self.defer_search:  # this command's step runs after it (search_step)
                self._search_due = True
                return None
            try:  # one step of the search per command (transfer/holes.py); its result used when it ends
                next(self._search)
                return None
            except StopIteration as done:
                self._search, hole = None, done.value
        if hole is None or store.is_configured(hole[0]):
            return None
        self._fill_cell, u = hole
        self._fill_tokens -= 1.0
        return u

    def search_step(self) -> bool:
        """With :attr:`defer_search`: the step of the hole search the last command asked for, run now, between two
        commands (its result, when the search ends, is the next fill's); True when there was one. It sees the store
        as that command's step would have, if it runs before the next pair is added: a station runs it after its
        command went out and before its next tick (:meth:`bridge.nodes.station_core.StationCore.background`), so
        its commands are the same whenever in between it runs, and the search's whole cost is off the commands'
        way. A search deferred so ends a command later than run in the command: its burst begins one command
        later."""
        if not self._search_due:
            return False
        self._search_due = False
        if self._search is None:
            return False
        try:
            next(self._search)
        except StopIteration as done:
            self._search, self._search_done = None, (done.value,)
        return True

    def _in_burst(self, c: tuple[int, int], u: NDArray[np.float64]) -> NDArray[np.float64] | None:
        """Where a burst's next command goes: ``u`` moved (on the yaw-rate axis) into the burst's cell ``c`` when it
        lies within one cell of it (a cell is finished at a yaw-rate error of at most one cell); else ``u`` if its
        own cell is unconfigured (the burst moves there); else None."""
        store, lb = self.store, self.store.learner_bounds
        l_n = lb.normalise(u)
        inside = self._nearest_in_cell(c, l_n)
        if abs(inside[1] - l_n[1]) <= 1.0 / store.grid[1]:
            return lb.clip(lb.denormalise(np.array([l_n[0], inside[1]])))
        return None if store.is_configured(store.cell_of(u)) else u

    def _fill_target(self, t: NDArray[np.float64]) -> tuple[tuple[int, int], NDArray[np.float64]] | None:
        """A whole hole search at once (:func:`transfer.holes.hole_search` run to its end): (cell, learner command)
        or None. :meth:`_fill` runs it a step per command instead."""
        return run_search(hole_search(self, t))

    def _at_speed(self, t: NDArray[np.float64], v_n: float, s: float) -> NDArray[np.float64] | None:
        """The learner command at normalised learner speed ``v_n`` whose yaw rate is the map's for ``s * omega_T``
        at the teacher's own speed ``v_T``, where the mission drives and the map is learned: the teacher's curvature
        at ``s * v_T``, if the learner's yaw-rate response does not depend on its speed. None when the map has no
        learned region for that yaw rate."""
        tb = self.store.teacher_bounds
        t_w = np.array([t[0], t[1] * s])
        u_w, method, _, _ = self._unperturbed(t_w, tb.normalise(t_w))
        if method == "direct":
            return None
        return self._at_learner_speed(u_w, v_n)

    def _at_learner_speed(self, u: NDArray[np.float64], v_n: float) -> NDArray[np.float64]:
        """Learner command ``u`` with its speed replaced by normalised learner speed ``v_n``, clipped to the box."""
        lb = self.store.learner_bounds
        l_n = lb.normalise(u)
        l_n[0] = v_n
        return lb.clip(lb.denormalise(l_n))

    def _cell_distance(self, cell: tuple[int, int], p: NDArray[np.float64]) -> float:
        """Distance (normalised learner units) from p to the rectangle of a grid cell."""
        g = np.array(self.store.grid, dtype=float)
        lo = np.array(cell, dtype=float) / g
        hi = lo + 1.0 / g
        return float(np.hypot(*(clamp(p, lo, hi) - p)))

    def _nearest_in_cell(self, cell: tuple[int, int], p: NDArray[np.float64]) -> NDArray[np.float64]:
        """The point of a cell nearest to p, ``inset`` of a cell inside its edges (so it falls in that cell)."""
        g = np.array(self.store.grid, dtype=float)
        lo = np.array(cell, dtype=float) / g
        margin = max(self.inset, 1e-6) / g
        return clamp(p, lo + margin, lo + 1.0 / g - margin)

    def _guided_target(self, cell: tuple[int, int], est_n: NDArray[np.float64],
                       plan: Plan) -> tuple[int, int] | None:
        """The unconfigured neighbour of ``cell`` that costs the least detour now and serves the plan best."""
        gv, gw = self.store.grid
        configured = self.store.configured()
        i0, j0 = cell
        cands = [(i, j) for i in range(max(0, i0 - 1), min(gv, i0 + 2)) for j in range(max(0, j0 - 1), min(gw, j0 + 2))
                 if (i, j) != cell and not configured[i, j]]
        if not cands:
            return None
        plan_est = self._plan_estimates(plan)
        cost = []
        for c in cands:
            k = self._cell_distance(c, est_n)
            if plan_est:
                k += min(self._cell_distance(c, p) for p in plan_est)
            cost.append(k)
        cost_a = np.array(cost)
        best = np.flatnonzero(cost_a <= cost_a.min() + 1e-9)
        return cands[int(best[self.rng.integers(best.size)])]

    def _plan_estimates(self, plan: Plan) -> list[NDArray[np.float64]]:
        """The normalised learner commands the teacher's planned commands would map to (region or estimate)."""
        if callable(plan):
            plan = plan()
        if plan is None:
            return []
        P = np.asarray(plan, dtype=float).reshape(-1, 2)
        out = []
        tb = self.store.teacher_bounds
        for p in P:
            if not np.all(np.isfinite(p)):
                continue
            p_n = tb.normalise(p)
            res = self._map_chain(p_n)
            out.append(res[0] if res is not None else self._estimate(p, p_n)[0])
        return out


POLICIES: dict[str, type[_PolicyBase]] = {"paper": PaperPolicy, "guided": GuidedPolicy}


def make_policy(store: PairStore, mapper: str | Mapper = "scm", rng: np.random.Generator | None = None, *,
                exploration: str = "guided", **options: float | int | str | None) -> Policy:
    """A policy by its exploration's name (``guided`` or ``paper``); ``options`` as the policies take them."""
    try:
        cls = POLICIES[exploration]
    except KeyError:
        raise ValueError(f"unknown exploration {exploration!r}; known: {', '.join(EXPLORATIONS)}") from None
    return cls(store, mapper, rng, **options)  # type: ignore[arg-type]
