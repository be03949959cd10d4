"""Forward models: a batch of parameter vectors -> simulated runouts per block size.

Both run every parameter vector with COMMON RANDOM NUMBERS: block j of every
size and every parameter vector uses the key ``fold_in(key, j)``, so the
runouts are a deterministic function of theta for a fixed key, and differences
between parameter vectors come from the parameters, not from the draws. That
makes finite differences and emulator designs far less noisy (Glasserman &
Yao 1992, "Some guidelines and guarantees for common random numbers").
``CrspForward.replicates`` deliberately does not: it draws independent block
sets at one theta, to measure the Monte Carlo error itself.

* ``CrspForward``: theta = (Kn, Kt, roughness_m), one set for the whole slope
  (with ``box=CRSP_ROLLING_BOX`` also the rolling resistance angle, with
  ``zoned_rolling_box`` one angle per material zone);
  block of size d is a sphere of radius d / 2, or the entry's shape class of
  the sphere's volume (``calib.model.entries``). One lane pool runs all
  (theta, size) tasks (``solvers.crsp.simulate_tasks``).
* ``DemForward``: theta = the damping law's parameters; a block of size d is a
  single square of side L = d with alpha(L) (``calib.model.alpha_law``, clipped as
  everywhere), run with ``calib.model.dem_run``'s numerics. The DEM runout of one
  size depends on theta only through alpha(L), so the emulator design runs
  each size on a grid of alpha values (``runouts_at_alpha``).

Unfinished blocks (status BUDGET or INVALID, ``solvers.status``) have no
runout: both return NaN for them, as runout and as passage speed, and every
consumer weights the finished blocks only (``calib.model.unfinished``). A block that
left the profile is finished; its runout is the one at the profile's end.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

import solvers.crsp as crsp
from calib.model.alpha_law import ALPHA_MAX, alpha_of
from calib.model.dem_run import DEM_RUN, DemRun
from calib.model.entries import Entries
from calib.model.priors import CRSP_BOX, DEM_BOXES, Box, rolling_zone, zoned_name
from calib.model.unfinished import mask_unfinished
from calib.model.warp import unwarp, warp, warped_box
from solvers.parallel import default_workers, map_ordered
from solvers.profile import Profile, segment_index

__all__ = ["CrspForward", "DemForward", "as_entries", "dem_lanes", "entry_blocks",
           "gather_entries", "lane_calls", "named_overrides", "release_rolling_deg",
           "release_slopes_deg", "rolling_columns", "split_by_profile", "stack_trees"]


@functools.partial(jax.jit, static_argnames=("rolling_cols",))
def _crsp_params(base: crsp.Params, theta: jax.Array, rolling_cols: tuple[int, ...] = ()
                 ) -> crsp.Params:
    """Per-task parameters: theta (T, 3 + k) sets Kn, Kt, roughness_m in every
    zone; ``rolling_cols`` (one theta column per zone, or ()) sets each zone's
    rolling_friction_deg (``rolling_columns``)."""
    n_t, n_z = theta.shape[0], base.Kn.shape[0]
    zone = lambda v: jnp.broadcast_to(v[:, None], (n_t, n_z))  # noqa: E731
    p = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (n_t,) + a.shape), base)
    p = p._replace(Kn=zone(theta[:, 0]), Kt=zone(theta[:, 1]),
                   roughness_m=zone(theta[:, 2]))
    if rolling_cols:
        p = p._replace(rolling_friction_deg=theta[:, jnp.asarray(rolling_cols)])
    return p


def rolling_columns(names, profile: Profile) -> tuple[int, ...]:
    """For each zone of ``profile``, the column of ``names`` that holds its
    rolling-resistance angle: ``rolling_friction_deg`` (every zone) or
    ``rolling_friction_deg[<zone>]`` (``calib.model.priors.zoned_rolling_box``);
    () when no column does (the profile's materials keep theirs). A ValueError
    when a zone has no column, or a zoned column is mixed with the global one.
    A zoned column for a zone this profile lacks is allowed (another profile of
    the same fit may have it)."""
    zones = {rolling_zone(n): j for j, n in enumerate(names) if rolling_zone(n) is not None}
    if not zones:
        return ()
    if "" in zones:
        if len(zones) > 1:
            raise ValueError("a rolling resistance for every zone (rolling_friction_deg) "
                             "and per zone cannot be fitted together")
        return (zones[""],) * len(profile.zone_names)
    missing = [z for z in profile.zone_names if z not in zones]
    if missing:
        raise ValueError(f"zoned rolling resistance: the profile's zone(s) "
                         f"{', '.join(missing)} have no parameter (expected "
                         f"{', '.join(zoned_name(z) for z in missing)})")
    return tuple(zones[z] for z in profile.zone_names)


def named_overrides(names, values, profile: Profile) -> dict:
    """``solvers.crsp.params_from_profile`` overrides of one parameter set
    (``names``, ``values``, e.g. a posterior draw): each zone's rolling
    resistance from its column (``rolling_columns``), the rest by name."""
    values = [float(v) for v in values]
    out = {n: v for n, v in zip(names, values, strict=True) if rolling_zone(n) is None}
    cols = rolling_columns(names, profile)
    if cols:
        out["rolling_friction_deg"] = np.asarray([values[c] for c in cols])
    return out


def _release_segments(profile: Profile, release_x_m, profiles=None) -> list:
    """[(the entry's profile, index of the segment its release lies on (the
    lower one at a vertex))] per release abscissa (``profiles``: each entry's
    own profile, None for ``profile``)."""
    rel = np.atleast_1d(np.asarray(release_x_m, float))
    own = profiles or (None,) * rel.shape[0]
    return [(profile if p is None else p,
             int(segment_index(profile if p is None else p, jnp.asarray(x0, jnp.float64))))
            for x0, p in zip(rel, own, strict=True)]


def release_slopes_deg(profile: Profile, release_x_m, profiles=None) -> np.ndarray:
    """(S,) the slope just below each release abscissa on its profile
    (``profiles``: the entry's own, None for ``profile``), that of the segment
    the release lies on (the lower one at a vertex), deg, > 0 downhill."""
    out = []
    for p, seg in _release_segments(profile, release_x_m, profiles):
        x, z = np.asarray(p.x_m, float), np.asarray(p.z_m, float)
        out.append(np.degrees(np.arctan2(z[seg] - z[seg + 1], x[seg + 1] - x[seg])))
    return np.asarray(out, float)


def release_rolling_deg(names, theta, profile: Profile, entries: Entries) -> np.ndarray:
    """(S, T) CRSP's rolling-resistance angle phi_r at each entry's release
    (the zone of the segment it lies on, ``release_slopes_deg``) for each of T
    parameter sets ``theta`` (T, p) with columns ``names``: the set's column
    for that zone (``rolling_columns``), or the profile's material value where
    no column fits it. A block at rest there starts rolling only where phi_r
    lies below the slope (``solvers.crsp._contact``)."""
    theta = np.atleast_2d(np.asarray(theta, float))
    out = np.empty((entries.n, theta.shape[0]))
    for i, (p, seg) in enumerate(_release_segments(profile, entries.release_x_m,
                                                   entries.profiles)):
        zone = int(p.zone_id[seg])
        cols = rolling_columns(names, p)
        out[i] = theta[:, cols[zone]] if cols else float(p.rolling_friction_deg[zone])
    return out


def lane_calls(side_m, alpha, max_width: int) -> list[np.ndarray]:
    """The DEM lanes (one block each, side ``side_m`` and damping ``alpha``,
    arrays of one value per lane) of each ``dem_lanes`` call, as index arrays:
    every call holds lanes of one side only, ordered by alpha, and all calls
    have one width w; a side's last call is padded by repeating its last lane.
    The largest side's n lanes need k = ceil(n / ``max_width``) calls, and w =
    ceil(n / k) spreads them evenly (33 lanes: two calls of 17, not 32 + 1).

    A vmapped call runs until its slowest lane stops, so lanes that take alike
    many steps belong in one call. The step count follows the side first: the
    stable step shrinks with the block (``solvers.dem.stable_dt``), and on
    Postignano a 0.2 m block at alpha 0.95 creeps to rest in about 1.3 million
    steps (142 s of simulated time) against about 0.1 million for a 2 m block
    (measured in the main job's DEM gradient stage: a call holding both sizes
    runs for the 0.2 m blocks' steps on all its lanes; docs/studies.md, "The
    DEM's lanes by block size"). Within a side the damping sets how fast a
    block moves. One width makes one compiled program serve every call; a
    width fitted to the largest side keeps a run from simulating mostly
    padding.

    The calls set the cost of a run, not its results: a lane's result does not
    depend on the lanes it shares a call with or on its place in it
    (``solvers.dem._sums``; tests/test_dem_lanes.py), so a padded lane repeats
    its original's result exactly."""
    side = np.asarray(side_m, float)
    if side.size == 0:
        return []
    order = np.lexsort((np.broadcast_to(np.asarray(alpha, float), side.shape), side))
    groups = np.split(order, np.flatnonzero(np.diff(side[order]) != 0) + 1)
    largest = max(len(g) for g in groups)
    width = -(-largest // -(-largest // int(max_width)))  # its calls as even as they come
    calls = []
    for g in groups:
        for c0 in range(0, len(g), width):
            idx = g[c0:c0 + width]
            calls.append(np.concatenate([idx, np.full(width - len(idx), idx[-1])]))
    return calls


def entry_blocks(entries: Entries, alpha: float, n_fragments: int = 1) -> list:
    """One DEM block (``solvers.dem.make_block``) per entry: a square of side
    ``Entries.dem_side_m`` damped by ``alpha``, released at the entry's point,
    height and speed with their errors' sds (``solvers.dem.Block``: a block
    draws a tracked height and speed as CRSP's blocks do; NaN keeps the DEM's
    release rule)."""
    from solvers.dem import make_block

    e = entries
    return [make_block(float(L), alpha=alpha, n_fragments=n_fragments, release_x_m=float(x),
                       release_speed_m_s=float(v), release_height_m=float(h),
                       release_height_sd_m=float(sh), release_speed_sd_m_s=float(sv))
            for L, x, v, h, sh, sv in zip(e.dem_side_m, e.release_x_m, e.release_speed_m_s,
                                          e.release_height_m, e.release_height_sd_m,
                                          e.release_speed_sd_m_s, strict=True)]


@functools.partial(jax.jit, static_argnames=("options",))
def dem_lanes(params, blocks, keys, options):
    """DEM ``simulate`` vmapped over (block, key) lanes; one cache for every forward."""
    from solvers.dem import simulate

    return jax.vmap(lambda b, k: simulate(params, b, k, options))(blocks, keys)


def as_entries(entries, profile: Profile) -> Entries:
    """``entries`` as ``Entries``: an ``Entries`` as it is, or an array of block
    sizes (m), one entry each, released at ``profile``'s first vertex at the
    solver's default speed and height (the solvers' own default release)."""
    if isinstance(entries, Entries):
        return entries
    return Entries.at_sizes(entries, float(profile.x_m[0]))


def split_by_profile(fw) -> list | None:
    """One forward per profile of ``fw.entries`` (``Entries.by_profile``):
    [(sub-forward, entry indices), ...], each sub-forward ``fw`` on its
    profile's entries, or None where every entry runs on ``fw.profile``.
    Shared by every forward model."""
    parts = fw.entries.by_profile(fw.profile)
    if parts is None:
        return None
    return [(dataclasses.replace(fw, profile=p, entries=fw.entries.take(idx)), idx)
            for p, idx in parts]


def gather_entries(parts, n_s: int, run):
    """Results of the sub-forwards of ``split_by_profile`` in entry order:
    ``run(sub, idx)`` gives an array, or a tuple of arrays, whose SECOND axis
    is the sub-forward's entries; the output has ``n_s`` entries there."""
    out, single = None, False
    for sub, idx in parts:
        res = run(sub, idx)
        single = not isinstance(res, tuple)
        res = (res,) if single else res
        if out is None:
            out = [np.full(r.shape[:1] + (n_s,) + r.shape[2:], np.nan) for r in res]
        for o, r in zip(out, res, strict=True):
            o[:, idx] = r
    return out[0] if single else tuple(out)


def stack_trees(trees):
    """Stack a list of pytrees (blocks) leaf by leaf into one batched pytree."""
    return jax.tree_util.tree_map(lambda *a: jnp.stack(a), *trees)


@dataclasses.dataclass
class CrspForward:
    """CRSP runouts for parameter vectors theta = (Kn, Kt, roughness_m).

    Attributes:
        profile: slope (its materials give the fixed parameters, e.g. rolling friction).
        entries: what is simulated (``calib.model.entries.Entries``: per entry a
            block size d and CRSP shape class, a release abscissa, speed and
            height, a profile, and the rock density that sets the mass), or an
            array of block sizes (m), one entry each released at the
            profile's first vertex. Entries need not have distinct sizes: an
            entry is a (size, release) group, e.g. the held-out rows of
            ``calib.inference.predictive_check``. A tracked release speed is the
            block's horizontal release velocity (``release_vx_m_s``; released
            on the ground it then rolls along the slope at speed times
            cos(slope)), the direction of a tracked release being seldom known
            (our choice); a release height starts the block in flight at that
            height (``solvers.crsp.init``). The entries' release errors
            (``Entries.release_height_sd_m``, ``release_speed_sd_m_s``) become
            each task's ``Params`` of the same names: every block draws its own
            height and speed (``solvers.crsp.init``: truncated normals; a
            negative height is a release from the error's tail above the
            ground, or on the ground with sd 0). An entry on a profile of its own
            runs as its own forward with the same theta, key and settings, so
            its runouts do not depend on the other entries.
        n_blocks: blocks per (theta, size).
        key: PRNG key shared by all thetas (common random numbers).
        pool: lanes of the scheduler (default ``solvers.crsp.default_pool()``); results do
            not depend on it, only the speed does.
        task_chunk: (theta, size) tasks per compiled call on one worker
            (default 96), divided by the number of worker threads.
        box: prior box of theta. Without an effect: (Kn, Kt, roughness_m), e.g.
            ``CRSP_BOX``, or with the rolling resistance angle fourth
            (``CRSP_ROLLING_BOX``), or one angle per zone of the profile(s)
            (``zoned_rolling_box``), or a narrower box of the same names. With an
            effect: that baseline box, to which the effect's columns and their
            stock ranges are appended (``calib.model.effects.full_box``; the
            baseline's ranges are kept), or a box that already ends with the
            effect's columns, taken as given (a custom range of the effect; also
            what ``dataclasses.replace`` passes back, so the columns are never
            added twice).
        effect: a candidate effect of ``calib.model.effects`` switched on ("none": plain
            CRSP), or a tuple of them switched on together (``effects.effect_names``:
            each has its own solver fields, so any distinct ones combine); their
            parameters follow the baseline's in theta, effect after effect.
        stations_x_m: abscissae (m) at which ``simulate`` records passage speeds.
        settings: CRSP solver settings (event budget, search window).
        rolling_threshold_m_s: CRSP's rolling threshold, m/s (the normal speed
            below which a landing or rebound rolls on, ``solvers.crsp.Params``):
            the site's (``calib.files.site``), recorded in ``calibration.json``;
            default ``solvers.crsp.ROLLING_THRESHOLD_M_S``.
    """

    profile: Profile
    entries: Entries
    n_blocks: int
    key: jax.Array
    pool: int = dataclasses.field(default_factory=crsp.default_pool)
    task_chunk: int = 96
    box: Box = CRSP_BOX
    effect: str | tuple[str, ...] = "none"
    stations_x_m: tuple[float, ...] = ()
    settings: crsp.Settings = crsp.Settings()
    rolling_threshold_m_s: float = crsp.ROLLING_THRESHOLD_M_S

    def __post_init__(self):
        self.entries = as_entries(self.entries, self.profile)
        if self.effect != "none":
            from calib.model.effects import effect_box, full_box

            extra = effect_box(self.effect, self.profile)
            n_base = self.box.dim - extra.dim
            if n_base < 0 or self.box.names[n_base:] != extra.names:
                # box is the baseline: the effect's columns follow it
                self.box = full_box(self.effect, self.profile, base=self.box)
            else:  # box already ends with them: kept, its baseline checked as full_box does
                full_box(self.effect, self.profile, base=Box(
                    *(v[:n_base] for v in (self.box.names, self.box.lower, self.box.upper))))
        rolling_columns(self.box.names, self.profile)  # every zone has its phi_r, or none
        self._parts = split_by_profile(self)  # entries on other profiles: own forwards

    @property
    def names(self) -> tuple[str, ...]:
        return self.box.names

    @property
    def sizes_m(self) -> np.ndarray:
        """(S,) block size of each entry, m."""
        return self.entries.sizes_m

    @property
    def n_rolling(self) -> int:
        """theta's rolling-resistance columns after (Kn, Kt, S): 0, 1
        (``CRSP_ROLLING_BOX``) or one per zone (``zoned_rolling_box``)."""
        return sum(rolling_zone(n) is not None for n in self.box.names[3:])

    def params(self, theta) -> crsp.Params:
        """Per-task CRSP parameters (T, ...) from theta (T, 3 + k): Kn, Kt and S
        for all zones, the rolling resistance for all zones or per zone."""
        theta = np.atleast_2d(np.asarray(theta, float))
        n_core = 3 + self.n_rolling
        p = _crsp_params(crsp.params_from_profile(
                             self.profile, rolling_threshold_m_s=self.rolling_threshold_m_s),
                         jnp.asarray(theta[:, :n_core], jnp.float64),
                         rolling_columns(self.box.names[:n_core], self.profile))
        if self.effect == "none":
            return p
        from calib.model.effects import crsp_overrides

        extra = crsp_overrides(self.effect, theta[:, n_core:], self.profile)
        return p._replace(**{k: jnp.asarray(v, jnp.float64) for k, v in extra.items()})

    def runouts(self, theta) -> np.ndarray:
        """Runouts (T, S, n_blocks), m, for theta (T, 3 + k); NaN for a block
        that did not finish (module docstring)."""
        return self.simulate(theta)[0]

    def simulate(self, theta) -> tuple[np.ndarray, np.ndarray]:
        """Runouts (T, S, n_blocks), m, and passage speeds (T, S, n_stations,
        n_blocks), m/s (NaN where a block did not pass), for theta (T, 3 + k).
        Both are NaN for every block that did not finish (status BUDGET or
        INVALID): its runout and its passages are not results.

        Tasks (theta, size) run in chunks of ``task_chunk`` divided among the
        worker threads (``solvers.parallel``: 48 tasks per chunk on 2 CPU
        cores, chunks side by side; the last one padded by repeating a task),
        so every call reuses one compiled program, whatever its ``n_blocks`` up to
        256 (``crsp.task_slots``: block counts are traced; the pool is not cut to
        the block count, which would compile it again).
        """
        theta = np.atleast_2d(np.asarray(theta, float))
        n_t, n_s = theta.shape[0], len(self.sizes_m)
        if self._parts is not None:
            return self._simulate_parts(theta)
        e = self.entries
        rep = np.repeat(theta, n_s, axis=0)  # task = (t, s)
        entry, release, speed, height, height_sd, speed_sd = (np.tile(v, n_t) for v in (
            np.arange(e.n), e.release_x_m, e.release_speed_m_s, e.release_height_m,
            e.release_height_sd_m, e.release_speed_sd_m_s))
        n_tasks = rep.shape[0]
        chunk = max(1, -(-self.task_chunk // default_workers()))
        pad = (-n_tasks) % chunk
        rep = np.concatenate([rep, np.repeat(rep[-1:], pad, axis=0)])
        entry, release, speed, height, height_sd, speed_sd = (
            np.concatenate([v, np.repeat(v[-1:], pad)])
            for v in (entry, release, speed, height, height_sd, speed_sd))
        stations = jnp.asarray(np.asarray(self.stations_x_m, float).reshape(-1), jnp.float64)

        def one_chunk(c0: int):
            params = self.params(rep[c0:c0 + chunk])
            s, h = speed[c0:c0 + chunk], height[c0:c0 + chunk]  # NaN: the solver's default
            params = params._replace(
                release_x_m=jnp.asarray(release[c0:c0 + chunk], jnp.float64),
                release_vx_m_s=jnp.asarray(np.where(
                    np.isfinite(s), s, np.broadcast_to(params.release_vx_m_s, s.shape)),
                    jnp.float64),
                release_height_m=jnp.asarray(np.where(
                    np.isfinite(h), h, np.broadcast_to(params.release_height_m, h.shape)),
                    jnp.float64),
                release_height_sd_m=jnp.asarray(height_sd[c0:c0 + chunk], jnp.float64),
                release_speed_sd_m_s=jnp.asarray(speed_sd[c0:c0 + chunk], jnp.float64))
            blocks = stack_trees(e.crsp_blocks(entry[c0:c0 + chunk]))
            res = crsp.simulate_tasks(params, blocks, self.key, self.profile, stations,
                                      n_per_task=self.n_blocks,
                                      pool=self.pool, settings=self.settings)
            status = np.asarray(res.status)  # (chunk, n)
            v = np.where(np.asarray(res.stations.passed), res.stations.velocity_m_s, np.nan)
            return mask_unfinished(res.runout_m, status), mask_unfinished(v, status)

        # task chunks side by side on the CPU cores (solvers.parallel), in order
        runs, speeds = [], []
        for r, v in map_ordered(one_chunk, range(0, rep.shape[0], chunk)):
            runs.append(r)
            speeds.append(v)  # (chunk, n, K)
        n_st = stations.shape[0]
        r = np.concatenate(runs)[:n_tasks].reshape(n_t, n_s, self.n_blocks)
        v = np.concatenate(speeds)[:n_tasks].reshape(n_t, n_s, self.n_blocks, n_st)
        return r, np.moveaxis(v, 3, 2)

    def _simulate_parts(self, theta) -> tuple[np.ndarray, np.ndarray]:
        """``simulate`` of entries on several profiles: one forward per profile."""
        return gather_entries(self._parts, len(self.sizes_m), lambda sub, _: sub.simulate(theta))

    def replicates(self, theta, reps: int, key: jax.Array) -> np.ndarray:
        """Runouts (reps, S, n_blocks), m, of ONE theta (p,) with ``reps``
        independent block sets drawn from ``key`` (not the common random numbers):
        the spread across them is the Monte Carlo error of anything computed from
        ``n_blocks`` blocks per size."""
        return self.replicate_sims(theta, reps, key)[0]

    def replicate_sims(self, theta, reps: int, key: jax.Array) -> tuple[np.ndarray, np.ndarray]:
        """``simulate`` of ONE theta (p,) with ``reps`` independent block sets
        (``replicates``): runouts (reps, S, n) and speeds (reps, S, n_stations, n)."""
        wide = dataclasses.replace(self, n_blocks=reps * self.n_blocks, key=key,
                                   task_chunk=len(self.sizes_m))
        r, v = wide.simulate(np.asarray(theta, float)[None])
        r = r[0].reshape(len(self.sizes_m), reps, self.n_blocks).transpose(1, 0, 2)
        v = v[0].reshape(len(self.sizes_m), -1, reps, self.n_blocks).transpose(2, 0, 1, 3)
        return r, v

    def design(self, n_design: int, seed: int):
        """Scrambled-Sobol design over the prior box, space-filling in the
        EMULATOR's coordinates (``to_input``: Kn, log(1 - Kt), log S[, tan(phi_r)]).

        Our choice, and why: the GP (one length scale per input) assumes a
        response about as smooth everywhere in these coordinates, so that is
        where its design should fill space (space-filling designs for computer
        experiments: Santner, Williams & Notz 2003, ch. 5). The prior stays uniform in theta
        (``calib.model.priors``); the design is where the emulator learns, not a
        prior sample. Measured on the Tschamut rows (96 points, 256 blocks,
        seed 3): a design uniform in theta put ~1 % of its points at S < 0.1 m,
        where the likelihood peaks, and its best point scored a summed
        log-likelihood of -3,724; uniform in these coordinates, 10 points
        scored above -1,000 and the best -553.

        Returns:
            (X, runouts): X (n_design, d) emulator inputs (``to_input`` of the
            thetas); runouts (n_design, S, n_blocks).
        """
        x = self.design_points(n_design, seed)
        return self.to_input(x), self.runouts(x)

    def design_points(self, n_design: int, seed: int) -> np.ndarray:
        """theta (n_design, d) of ``design``, not simulated."""
        from scipy.stats import qmc

        z = qmc.Sobol(self.box.dim, scramble=True, seed=seed).random_base2(
            int(np.ceil(np.log2(n_design))))[:n_design]
        return np.clip(self.from_input(self.input_box.from_unit(z)), self.box.lo, self.box.hi)

    def to_input(self, theta):
        """Emulator coordinates (Kn, log(1 - Kt), log S[, tan(phi_r)];
        ``calib.model.warp``): in these the response is closer to stationary,
        which a GP with one length scale per input assumes (input warping)."""
        return warp(self.box.names, theta)

    def from_input(self, x) -> np.ndarray:
        """theta (..., d) from emulator coordinates (..., d): the inverse of ``to_input``."""
        return unwarp(self.box.names, x)

    def emulator_inputs(self, theta):
        """Emulator input of each size for theta (d,) -> (S, d)."""
        return jnp.broadcast_to(self.to_input(theta), (len(self.sizes_m), self.box.dim))

    @property
    def input_box(self) -> Box:
        return warped_box(self.box)


@dataclasses.dataclass
class DemForward:
    """DEM runouts of single square blocks for the damping law alpha(L).

    Attributes:
        profile: slope.
        entries: what is simulated (``calib.model.entries.Entries``: square side
            L = d, release, speed, height, profile, density), or an array of
            block sizes, as in ``CrspForward``. A NaN release speed or height
            keeps the DEM's release rule (``solvers.dem.Params``: 1 cm above the
            ground, speed uniform in 0-1 m/s); the DEM still offsets each block
            up to 0.5 m downslope and turns it at random. A tracked release
            height and speed carry the entries' errors: each block draws them
            as CRSP's blocks do (``entry_blocks``). The density sets the
            mass per metre of width, with which the contact and damping
            forces scale.
        n_blocks: blocks per (alpha, size); few, the DEM is expensive.
        key: PRNG key shared by all (common random numbers).
        form: "power" or "constant" (``calib.model.alpha_law``).
        run: DEM numerics (stiffness scale, time limit, step bound;
            ``calib.model.dem_run``), the hazard run's too.
        lane_batch: blocks per compiled call at most; the calls of one run hold
            one block side each and share one width (``lane_calls``).
    """

    profile: Profile
    entries: Entries
    n_blocks: int
    key: jax.Array
    form: str = "power"
    run: DemRun = DEM_RUN
    lane_batch: int = 32

    def __post_init__(self):
        self.entries = as_entries(self.entries, self.profile)
        self._parts = split_by_profile(self)
        if self.form not in DEM_BOXES:
            raise ValueError(f"unknown alpha law form {self.form!r}; expected one of "
                             f"{', '.join(DEM_BOXES)}")
        self._params = self.run.params(self.profile, rho=self.entries.density_kg_m3)
        self._fn = None

    @property
    def box(self) -> Box:
        return DEM_BOXES[self.form]

    @property
    def names(self) -> tuple[str, ...]:
        return self.box.names

    @property
    def sizes_m(self) -> np.ndarray:
        """(S,) block size of each entry, m."""
        return self.entries.sizes_m

    @property
    def input_box(self) -> Box:
        return Box(("alpha",), (0.0,), (ALPHA_MAX,))

    def _compiled(self):
        if self._fn is None:
            options = self.run.options(self._params, self.entries.dem_side_m,
                                       release_errors=self.entries.has_release_errors)
            self._fn = functools.partial(dem_lanes, self._params, options=options)
        return self._fn

    def runouts_at_alpha(self, alpha) -> np.ndarray:
        """Runouts (T, S, n_blocks), m, for per-size damping alpha (T, S); NaN for
        a block that did not finish (status BUDGET or INVALID)."""
        alpha = np.asarray(alpha, float)
        n_t, n_s = alpha.shape
        if self._parts is not None:  # one forward per profile (Entries.profiles)
            return gather_entries(self._parts, n_s,
                                  lambda sub, idx: sub.runouts_at_alpha(alpha[:, idx]))
        e = self.entries
        proto = entry_blocks(e, alpha=0.5)
        lanes, keys = [], []
        for t in range(n_t):
            for s in range(n_s):
                for j in range(self.n_blocks):
                    lanes.append(proto[s]._replace(alpha=jnp.full((1,), alpha[t, s])))
                    keys.append(j)
        calls = lane_calls(np.tile(np.repeat(e.dem_side_m, self.n_blocks), n_t),
                           np.repeat(alpha, self.n_blocks, axis=1).ravel(), self.lane_batch)
        fn = self._compiled()
        runouts = np.empty(len(lanes))
        for idx in calls:
            k = jax.vmap(lambda j: jax.random.fold_in(self.key, j))(
                jnp.asarray([keys[i] for i in idx], jnp.uint32))
            res = fn(stack_trees([lanes[i] for i in idx]), k)  # runout_m (lanes, 1), status
            runouts[idx] = mask_unfinished(np.asarray(res.runout_m)[:, 0], res.status)
        return runouts.reshape(n_t, n_s, self.n_blocks)

    def alphas(self, theta) -> np.ndarray:
        """alpha per size (T, S) for theta (T, n_params)."""
        return np.asarray(alpha_of(self.form, np.atleast_2d(theta), self.entries.dem_side_m))

    def runouts(self, theta) -> np.ndarray:
        """Runouts (T, S, n_blocks), m, for law parameters theta (T, n_params)."""
        return self.runouts_at_alpha(self.alphas(theta))

    def design(self, n_design: int, seed: int):
        """alpha grid (same for every size; seed unused, the grid is deterministic).

        Returns:
            (X, runouts): X (n_design, 1) alpha; runouts (n_design, S, n_blocks).
        """
        del seed
        a = np.linspace(0.02, ALPHA_MAX, n_design)
        return a[:, None], self.runouts_at_alpha(np.repeat(a[:, None], len(self.sizes_m), 1))

    def emulator_inputs(self, theta):
        """Emulator input of each size: its alpha(L) -> (S, 1)."""
        return alpha_of(self.form, jnp.asarray(theta), self.entries.dem_side_m)[:, None]
