"""How well a map predicts lidar rays it was not built from: held-out scores, side by side
with classic occupancy, and the empirical-Bayes prior (``score`` and ``fit-prior``).

Every scored ray is placed by the replay's pipeline and walked by ``core.likelihood``: each
voxel crossed before its return is an event "passed", the return voxel an event "returned
here" (over its full chord). Per model, over all events: ``log_likelihood_per_ray`` (sum of
the events' log-probabilities / rays), ``log_loss_per_event``, ``brier`` (mean squared
error of the predicted return probability), ``ece`` (expected calibration error on 10
equal-width bins of predicted probability, Guo et al. 2017), ``ece_log`` (the same on the
log-spaced bins: most events are predicted below 0.1, where equal-width bins see one bin),
``log_density_per_ray`` (the log-likelihood with each return voxel's probability turned
into a density of the return's range, divided by the voxel's full chord: nats with ranges
in metres, comparable between resolutions, where the per-ray log-likelihood is not: a
coarser voxel locates a return less precisely and so predicts it more easily)
and the calibration tables (``calibration``: equal-width bins; ``calibration_log``:
log-spaced; each bin: count, mean predicted, observed frequency).

Classic occupancy (Eq. 5) is built from the same training rays: OctoMap's log-odds update
per scan (a voxel holding a return of the scan +0.85, else crossed -0.4, clamped to [-2,
3.5]), and an event in a voxel of occupancy ``p_o`` has return probability ``a (1 - p_o) + b
p_o`` — the paper's a = 0.2, b = 0.47 (``classic_paper``), or a and b fitted by maximum
likelihood on the scored events themselves (``classic_fitted``: the best that model can do,
an upper bound).

Reflectivity (Appendix B; ``ReflectivityScore``): when the map holds intensity histograms and
the held-out scans have the same intensity field, each held-out return's intensity bin is
scored under its voxel's histogram (decayed to the scan's time) smoothed toward the global
histogram of all training returns by a Dirichlet prior of total weight
``REFLECTIVITY_CONCENTRATION``: ``(n_j + c g_j) / (n + c)`` (a voxel without returns
predicts ``g``); ``reflectivity.baseline_per_return`` scores the same returns under ``g``
alone. ``g`` is the map's histograms summed (at the latest time), with half a return added to
every bin so that no bin has probability 0.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mfp_mapper.core.likelihood import ScanEvents, score_rays
from mfp_mapper.core.mapper import IntegrationSummary, Mapper
from mfp_mapper.core.model import UNIFORM, Prior, family_prior
from mfp_mapper.core.reflectivity import smoothed
from mfp_mapper.mapping.loop import integrate_scan
from mfp_mapper.sensing.pipeline import PlacedScan, ScanDropped
from mfp_mapper.sources.recording import Recording

FloatArray = NDArray[np.float64]

LINEAR_EDGES = np.linspace(0.0, 1.0, 11)
"""Bins of predicted probability of the ECE and of the ``calibration`` table."""
LOG_EDGES = np.concatenate([[0.0], np.logspace(-5.0, 0.0, 16)])
"""Bins of the ``calibration_log`` table: most events are predicted far below 0.1."""
CLASSIC_HIT = 0.85
CLASSIC_MISS = -0.4
CLASSIC_MIN = -2.0
CLASSIC_MAX = 3.5
PAPER_A = 0.2
"""Classic forward model: return probability in a free voxel (Eq. 5, Fig. 9)."""
PAPER_B = 0.47
"""Classic forward model: return probability in an occupied voxel."""
_KEY_BITS = 21
_KEY_OFFSET = 1 << (_KEY_BITS - 1)
REFLECTIVITY_CONCENTRATION = 1.0
"""Total weight c (returns) of the Dirichlet prior that smooths a voxel's reflectivity
histogram toward the global one: chosen by leave-one-scan-out on ouster_street (each scan
predicted by the other two) over c in {0.5, 1, 2, 4, 8} at 8 bins: c = 1 scored best or within
0.01 nats/return of the best at 0.1 and 0.2 m (docs/scoring.md)."""
GLOBAL_PSEUDO_COUNT = 0.5
"""Returns added to every bin of the global histogram (no bin of probability 0)."""


class Metrics:
    """Scores accumulated over events: log-likelihood, Brier, calibration bins."""

    def __init__(self) -> None:
        self.rays = 0
        self.events = 0.0
        self.log_likelihood = 0.0
        self.brier = 0.0
        self.impossible = 0.0
        """Events whose outcome had probability 0 (log-probability -inf)."""
        self.linear = np.zeros((3, LINEAR_EDGES.size - 1))  # count, sum p, sum y
        self.log = np.zeros((3, LOG_EDGES.size - 1))

    def add(
        self,
        p: FloatArray,
        y: NDArray[np.bool_] | FloatArray,
        log_p: FloatArray,
        weight: FloatArray | None = None,
    ) -> None:
        """Events with predicted return probability ``p``, outcome ``y`` (1: returned here),
        log-probability of the outcome ``log_p``; ``weight``: how many events each row is."""
        w = np.ones(p.shape) if weight is None else weight
        yf = np.asarray(y, dtype=np.float64)
        self.events += float(w.sum())
        self.log_likelihood += float(np.dot(w, log_p))
        self.impossible += float(w[np.isneginf(log_p)].sum())
        self.brier += float(np.dot(w, (p - yf) ** 2))
        for table, edges in ((self.linear, LINEAR_EDGES), (self.log, LOG_EDGES)):
            k = np.clip(np.searchsorted(edges, p, side="right") - 1, 0, edges.size - 2)
            for row, values in enumerate((w, w * p, w * yf)):
                table[row] += np.bincount(k, values, minlength=edges.size - 1)

    def result(self) -> dict[str, Any]:
        events = max(self.events, 1e-300)
        count, sum_p, sum_y = self.linear
        used = count > 0
        ece = float(np.sum(np.abs(sum_p[used] - sum_y[used])) / events)
        log_count, log_p, log_y = self.log
        ece_log = float(np.sum(np.abs(log_p - log_y)[log_count > 0]) / events)
        return {
            "rays": self.rays,
            "events": int(round(self.events)),
            "log_likelihood": self.log_likelihood,
            "log_likelihood_per_ray": self.log_likelihood / max(self.rays, 1),
            "log_loss_per_event": -self.log_likelihood / events,
            "impossible_events": int(round(self.impossible)),
            "brier": self.brier / events,
            "ece": ece,
            "ece_log": ece_log,
            "calibration": _table(self.linear, LINEAR_EDGES),
            "calibration_log": _table(self.log, LOG_EDGES),
        }


def _table(table: FloatArray, edges: FloatArray) -> list[dict[str, float]]:
    rows = []
    for k in range(edges.size - 1):
        count, sum_p, sum_y = table[:, k]
        if count <= 0:
            continue
        rows.append(
            {
                "lo": float(edges[k]),
                "hi": float(edges[k + 1]),
                "count": int(round(count)),
                "mean_predicted": float(sum_p / count),
                "observed_frequency": float(sum_y / count),
            }
        )
    return rows


def _pack(ijk: NDArray[np.integer]) -> NDArray[np.int64]:
    """One int64 per voxel index (21 bits an axis around the map's origin)."""
    v = ijk.astype(np.int64) + _KEY_OFFSET
    if v.size and (v.min() < 0 or v.max() >= 1 << _KEY_BITS):
        raise ValueError("classic occupancy: voxel indices beyond +-2^20 of the map's origin")
    return (v[:, 0] << (2 * _KEY_BITS)) | (v[:, 1] << _KEY_BITS) | v[:, 2]


class ClassicMap:
    """OctoMap-style log-odds per voxel, updated once per scan (a voxel holding a return of
    the scan is occupied for that scan, else free where the scan's rays crossed it)."""

    def __init__(self) -> None:
        self.keys = np.zeros(0, dtype=np.int64)
        self.log_odds = np.zeros(0)

    def update(self, events: ScanEvents) -> None:
        keys, inverse = np.unique(_pack(events.ijk), return_inverse=True)
        hit = np.zeros(keys.size, dtype=np.bool_)
        hit[inverse.ravel()[events.hit]] = True
        union = np.union1d(self.keys, keys)
        log_odds = np.zeros(union.size)
        log_odds[np.searchsorted(union, self.keys)] = self.log_odds
        at = np.searchsorted(union, keys)
        step = np.where(hit, CLASSIC_HIT, CLASSIC_MISS)
        log_odds[at] = np.clip(log_odds[at] + step, CLASSIC_MIN, CLASSIC_MAX)
        self.keys, self.log_odds = union, log_odds

    def lookup(self, ijk: NDArray[np.integer]) -> FloatArray:
        """Log-odds of these voxels (0, p_o = 0.5, where never updated)."""
        keys = _pack(ijk)
        at = np.clip(np.searchsorted(self.keys, keys), 0, max(self.keys.size - 1, 0))
        found = self.keys.size > 0
        out = np.zeros(keys.size)
        if found:
            hit = self.keys[at] == keys
            out[hit] = self.log_odds[at[hit]]
        return out


class ClassicCounts:
    """Scored events of classic occupancy, grouped by log-odds (p_o is a function of it):
    everything, a and b fitted included, follows from these counts exactly."""

    def __init__(self) -> None:
        self.counts: dict[float, list[float]] = {}
        self.rays = 0

    def add(self, log_odds: FloatArray, hit: NDArray[np.bool_]) -> None:
        rounded = np.round(log_odds, 9)
        values, inverse = np.unique(rounded, return_inverse=True)
        hits = np.bincount(inverse.ravel(), hit.astype(np.float64), minlength=values.size)
        total = np.bincount(inverse.ravel(), minlength=values.size)
        for v, h, t in zip(values.tolist(), hits.tolist(), total.tolist(), strict=True):
            entry = self.counts.setdefault(v, [0.0, 0.0])
            entry[0] += h
            entry[1] += t - h

    def arrays(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(p_o, returns, passes) per log-odds value."""
        keys = np.array(sorted(self.counts))
        p_o = 1.0 / (1.0 + np.exp(-keys)) if keys.size else np.zeros(0)
        hits = np.array([self.counts[k][0] for k in keys.tolist()])
        passes = np.array([self.counts[k][1] for k in keys.tolist()])
        return p_o, hits, passes

    def metrics(self, a: float, b: float) -> Metrics:
        p_o, hits, passes = self.arrays()
        p = np.clip(a * (1.0 - p_o) + b * p_o, 1e-12, 1.0 - 1e-12)
        m = Metrics()
        m.rays = self.rays
        m.add(p, np.ones(p.shape), np.log(p), hits)
        m.add(p, np.zeros(p.shape), np.log1p(-p), passes)
        return m

    def fit(self) -> tuple[float, float]:
        """a, b of largest likelihood of the counted events (0 < a, b < 1)."""
        from scipy.optimize import minimize

        p_o, hits, passes = self.arrays()

        def loss(x: FloatArray) -> float:
            a, b = 1.0 / (1.0 + np.exp(-x))
            p = np.clip(a * (1.0 - p_o) + b * p_o, 1e-15, 1.0 - 1e-15)
            return float(-(np.dot(hits, np.log(p)) + np.dot(passes, np.log1p(-p))))

        start = np.log(np.array([PAPER_A, PAPER_B]) / (1 - np.array([PAPER_A, PAPER_B])))
        best = minimize(loss, start, method="Nelder-Mead", options={"xatol": 1e-7, "fatol": 1e-9})
        a, b = 1.0 / (1.0 + np.exp(-best.x))
        return float(a), float(b)


class EventSample:
    """A weighted sample of scored events (s, n, chord, hit): enough for ``fit_prior``.

    Every return event is kept; pass events are kept with probability ``keep`` (weight
    1 / keep), halved whenever more than ``budget`` events are held."""

    def __init__(self, budget: int = 4_000_000, seed: int = 0) -> None:
        self.parts: list[tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_]]] = []
        self.weights: list[FloatArray] = []
        self.keep = 1.0
        self.budget = budget
        self.rays = 0
        self.rng = np.random.default_rng(seed)

    @property
    def size(self) -> int:
        return sum(p[0].size for p in self.parts)

    def add(self, ev: ScanEvents) -> None:
        take = ev.hit | (self.rng.random(len(ev)) < self.keep)
        self.parts.append((ev.s[take], ev.n[take], ev.chord[take], ev.hit[take]))
        self.weights.append(np.where(ev.hit[take], 1.0, 1.0 / self.keep))
        while self.size > self.budget and self.keep > 1e-6:
            self.keep *= 0.5
            for k, (s, n, chord, hit) in enumerate(self.parts):
                stay = hit | (self.rng.random(s.size) < 0.5)
                self.parts[k] = (s[stay], n[stay], chord[stay], hit[stay])
                self.weights[k] = np.where(hit[stay], 1.0, self.weights[k][stay] * 2.0)

    def arrays(self) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_], FloatArray]:
        if not self.parts:
            empty = np.zeros(0)
            return empty, empty, empty, np.zeros(0, dtype=np.bool_), empty
        s, n, chord, hit = (np.concatenate(cols) for cols in zip(*self.parts, strict=True))
        return s, n, chord, hit, np.concatenate(self.weights)


class ReflectivityScore:
    """Held-out returns' intensity bins under the map's smoothed histograms and under the
    global histogram (module docstring)."""

    def __init__(self, mapper: Mapper) -> None:
        self.mapper = mapper
        self.returns = 0
        self.log_likelihood = 0.0
        self.baseline = 0.0
        self._background: FloatArray | None = None

    def background(self) -> FloatArray:
        """The global histogram of the training returns (probabilities, J)."""
        if self._background is None:
            table = self.mapper.stored_reflectivity()
            assert table is not None
            counts = table.counts
            if len(table) and math.isfinite(self.mapper.decay_time):
                at = float(table.t_last.max())
                counts = counts * np.exp((table.t_last - at) / self.mapper.decay_time)[:, None]
            total = counts.sum(axis=0) + GLOBAL_PSEUDO_COUNT
            self._background = total / total.sum()
        return self._background

    def add(self, placed: PlacedScan, rays: Any) -> None:
        """Score the returns of the rays (``Mapper.place_rays`` of ``placed``) that carry an
        intensity of the map's field."""
        scale = self.mapper.reflectivity_scale
        if scale is None or placed.intensity is None or placed.intensity_field != scale.field:
            return
        picked = np.asarray(rays.source)[rays.has_return]
        bins = scale.bin_of(placed.intensity[picked])
        valid = bins >= 0
        if not valid.any():
            return
        found = self.mapper.reflectivity(placed.points[picked[valid]], placed.stamp)
        assert found is not None
        background = self.background()
        p = smoothed(found[1], background, REFLECTIVITY_CONCENTRATION)
        b = bins[valid]
        self.returns += int(b.size)
        self.log_likelihood += float(np.log(p[np.arange(b.size), b]).sum())
        self.baseline += float(np.log(background[b]).sum())

    def result(self) -> dict[str, Any] | None:
        """The ``reflectivity`` part of the report, None when no return was scored."""
        scale = self.mapper.reflectivity_scale
        if not self.returns or scale is None:
            return None
        per_return = self.log_likelihood / self.returns
        baseline = self.baseline / self.returns
        return {
            "returns": self.returns,
            "log_likelihood_per_return": per_return,
            "baseline_per_return": baseline,
            "gain_per_return": per_return - baseline,
            "field": scale.field,
            "bins": scale.count,
            "edges": list(scale.edges),
            "concentration": REFLECTIVITY_CONCENTRATION,
        }


class Scorer:
    """Scores placed scans against ``mapper`` (a ``ScanConsumer`` of the replay)."""

    def __init__(
        self,
        mapper: Mapper,
        priors: dict[str, Prior],
        classic: ClassicMap | None = None,
        sample: EventSample | None = None,
        rays: slice | None = None,
    ) -> None:
        self.mapper = mapper
        self.priors = priors
        self.metrics = {name: Metrics() for name in priors}
        self.classic = classic
        self.classic_counts = ClassicCounts()
        self.sample = sample
        self.ray_slice = rays
        self.return_log_chord = 0.0
        """Sum of log(full chord, m) of the return events: turns a return voxel's probability
        into a density of the return's range along the ray (``log_density_per_ray``)."""
        self.reflectivity = ReflectivityScore(mapper)
        self.echoes: EchoScores | None = None
        """The held-out echoes scored with maps of all echoes and of first echoes
        (``EchoMaps``), when the training had echoes."""

    def __call__(self, _replay_mapper: Mapper, placed: PlacedScan) -> IntegrationSummary:
        placed = select_rays(placed, self.ray_slice)
        if self.echoes is not None:
            self.echoes.score(placed)
        placed = first_echoes(placed)
        rays, dropped = self.mapper.place_rays(placed.points, placed.origins, placed.no_return)
        summary = IntegrationSummary(rays_in=placed.points.shape[0], dropped=dropped)
        summary.rays_used = len(rays)
        if not len(rays):
            raise ScanDropped("no_usable_rays", "no ray of the scan could be scored")
        _, _, ev = score_rays(self.mapper, rays, placed.stamp, events=True)
        assert ev is not None
        self.return_log_chord += float(np.log(ev.chord[ev.hit]).sum())
        for name, prior in self.priors.items():
            m = self.metrics[name]
            m.rays += len(rays)
            p = ev.hit_probability(prior.shape, prior.rate)
            m.add(p, ev.hit, ev.log_probability(prior.shape, prior.rate))
        if self.classic is not None:
            self.classic_counts.rays += len(rays)
            self.classic_counts.add(self.classic.lookup(ev.ijk), ev.hit)
        if self.sample is not None:
            self.sample.rays += len(rays)
            self.sample.add(ev)
        self.reflectivity.add(placed, rays)
        summary.voxels_touched = len(ev)
        return summary


def select_rays(placed: PlacedScan, rays: slice | None) -> PlacedScan:
    """The scan with only the rays ``rays`` selects (e.g. every other shot): of a scan with
    echoes (``placed.shot``), the rays of the shots it selects."""
    if rays is None:
        return placed
    if placed.shot is None:
        return _take(placed, rays)
    chosen = np.zeros(int(placed.shot.max(initial=-1)) + 1, dtype=np.bool_)
    chosen[rays] = True
    return _take(placed, chosen[placed.shot])


def _take(placed: PlacedScan, rays: slice | NDArray[np.bool_]) -> PlacedScan:
    """The scan with the rays ``rays`` selects (a slice or a mask)."""
    origins = placed.origins if placed.origins.ndim == 1 else placed.origins[rays]

    def pick(values: NDArray[Any] | None) -> NDArray[Any] | None:
        return None if values is None else values[rays]

    return replace(
        placed,
        points=placed.points[rays],
        origins=origins,
        no_return=pick(placed.no_return),
        intensity=pick(placed.intensity),
        shot=pick(placed.shot),
        continued=pick(placed.continued),
    )


def first_echoes(placed: PlacedScan) -> PlacedScan:
    """The scan with the first echo of each shot only (the rays from the sensor)."""
    if placed.continued is None:
        return placed
    return replace(_take(placed, ~placed.continued), continued=None)


def later_echoes(placed: PlacedScan) -> PlacedScan:
    """The rays of a scan's later echoes that carry a return and a chord: each from where
    the blind stretch after the echo before ends (echoes inside it are not scored)."""
    assert placed.continued is not None
    span = placed.points - placed.origins
    keep = placed.continued & (np.einsum("ij,ij->i", span, span) > 0.0)
    if placed.no_return is not None:
        keep &= ~placed.no_return
    return _take(placed, keep)


class EchoMaps:
    """Two maps of the training echoes (``score`` on an input with echoes): ``all`` (each
    shot one process along its beam) and ``first_only`` (its first echo). The replay's own
    map is the one the settings ask for; the other is built beside it."""

    def __init__(self) -> None:
        self.maps: dict[str, Mapper] = {}

    def add(self, mapper: Mapper, placed: PlacedScan) -> None:
        """Add a training scan with shots to both maps (``mapper``: the replay's)."""
        if not self.maps:
            twin = _empty_like(mapper)
            if placed.continued is None:  # the settings ask for first echoes only
                self.maps = {"all": twin, "first_only": mapper}
            else:
                self.maps = {"all": mapper, "first_only": twin}
        other = self.maps["first_only"] if self.maps["all"] is mapper else self.maps["all"]
        if other is self.maps["first_only"]:
            placed = first_echoes(placed)
        if len(placed.points):
            other.integrate(
                placed.points,
                placed.origins,
                placed.stamp,
                placed.no_return,
                continued=placed.continued,
            )


def _empty_like(mapper: Mapper) -> Mapper:
    """An empty map with ``mapper``'s settings."""
    return Mapper(
        mapper.resolution,
        max_range=mapper.max_range,
        min_range=mapper.min_range,
        decay_time=mapper.decay_time,
        frame_id=mapper.frame_id,
        threads=mapper.threads,
        max_voxels=mapper.max_voxels,
        keep_radius=mapper.keep_radius,
        origin=mapper.origin,
        prior_shape=mapper.prior.shape,
        prior_rate=mapper.prior.rate,
    )


class EchoScores:
    """Held-out shots scored by each map of ``EchoMaps``: the first echo as a ray from the
    sensor, each later echo given the echo before it (its ray from the end of that echo's
    blind stretch; the blind stretch is not scored), with each map's prior."""

    def __init__(self, maps: EchoMaps) -> None:
        self.maps = maps.maps
        self.sums = {name: np.zeros(4) for name in self.maps}  # first ll, rays, later ll, echoes
        self.in_blind = 0

    def score(self, placed: PlacedScan) -> None:
        first = first_echoes(placed)
        later = later_echoes(placed) if placed.continued is not None else None
        if placed.continued is not None and later is not None:
            self.in_blind += int(placed.continued.sum()) - len(later.points)
        for name, mapper in self.maps.items():
            sums = self.sums[name]
            for k, part in ((0, first), (2, later)):
                if part is None or not len(part.points):
                    continue
                rays, _ = mapper.place_rays(
                    part.points, part.origins, part.no_return, part.continued
                )
                if len(rays):
                    per_ray, _, _ = score_rays(mapper, rays, part.stamp)
                    sums[k] += float(per_ray.sum())
                    sums[k + 1] += len(rays)

    def result(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for name, (first, rays, later, echoes) in self.sums.items():
            out[name] = {
                "first_echo_log_likelihood_per_ray": first / max(rays, 1),
                "later_echo_log_likelihood_per_echo": later / max(echoes, 1),
                "first_echoes": int(rays),
                "later_echoes": int(echoes),
                "prior": _prior_json(self.maps[name].prior),
            }
        out["later_echoes_in_blind_stretch"] = self.in_blind
        return out


def training_consumer(
    classic: ClassicMap | None, rays: slice | None, echo_maps: EchoMaps | None = None
) -> Callable[[Mapper, PlacedScan], IntegrationSummary]:
    """Integrates each training scan (its ``rays``) and updates the classic map with it
    (from its first echoes); a scan with shots also goes into ``echo_maps``."""

    def consume(mapper: Mapper, placed: PlacedScan) -> IntegrationSummary:
        placed = select_rays(placed, rays)
        if classic is not None:
            first = first_echoes(placed)
            found, _ = mapper.place_rays(first.points, first.origins, first.no_return)
            if len(found):
                _, _, ev = score_rays(mapper, found, placed.stamp, events=True)
                assert ev is not None
                classic.update(ev)
        summary = integrate_scan(mapper, placed)
        if echo_maps is not None and placed.shot is not None:
            echo_maps.add(mapper, placed)
        return summary

    return consume


def report(scorer: Scorer, main: str) -> dict[str, Any]:
    """The JSON report: the ``main`` prior's scores at the top, the others by name, and
    classic occupancy when it was built."""
    out: dict[str, Any] = scorer.metrics[main].result()
    prior = scorer.priors[main]
    out["prior"] = {"shape": prior.shape, "rate": prior.rate}
    for name, m in scorer.metrics.items():
        if name != main:
            out[name] = {**m.result(), "prior": _prior_json(scorer.priors[name])}
    if scorer.classic is not None:
        paper = scorer.classic_counts.metrics(PAPER_A, PAPER_B).result()
        out["classic_paper"] = {**paper, "a": PAPER_A, "b": PAPER_B}
        a, b = scorer.classic_counts.fit()
        out["classic_fitted"] = {**scorer.classic_counts.metrics(a, b).result(), "a": a, "b": b}
    for part in [out, *(v for v in out.values() if isinstance(v, dict) and "rays" in v)]:
        part["log_density_per_ray"] = (part["log_likelihood"] - scorer.return_log_chord) / max(
            part["rays"], 1
        )
    reflectivity = scorer.reflectivity.result()
    if reflectivity is not None:
        out["reflectivity"] = reflectivity
    if scorer.echoes is not None:
        out["echoes"] = scorer.echoes.result()
    return out


def _prior_json(prior: Prior) -> dict[str, float]:
    return {"shape": prior.shape, "rate": prior.rate}


def summary_lines(report_: dict[str, Any], label: str = "") -> list[str]:
    """A few lines of the report for a terminal."""
    rows = [("this model", report_)]
    rows += [
        (name, value)
        for name, value in report_.items()
        if isinstance(value, dict) and "log_likelihood_per_ray" in value
    ]
    head = f"{label}{report_['rays']:,} rays, {report_['events']:,} events"
    lines = [
        head,
        f"{'model':<36} {'loglik/ray':>10} {'density/ray':>11} {'logloss/ev':>10} "
        f"{'brier':>8} {'ece':>8}",
    ]
    for name, r in rows:
        text = name
        if "prior" in r:
            text += f" (prior {r['prior']['shape']:.4g}, {r['prior']['rate']:.4g})"
        if "a" in r:
            text += f" (a {r['a']:.3f}, b {r['b']:.3f})"
        lines.append(
            f"{text:<36} {r['log_likelihood_per_ray']:>10.4f} {r['log_density_per_ray']:>11.4f} "
            f"{r['log_loss_per_event']:>10.5f} {r['brier']:>8.5f} {r['ece']:>8.5f}"
        )
    lines += [f"{name}: {why}" for name, r in rows if (why := nonfinite_reason(r)) is not None]
    refl = report_.get("reflectivity")
    if isinstance(refl, dict):
        lines.append(
            f"reflectivity ({refl['field']}, {refl['bins']} bins, {refl['returns']:,} returns): "
            f"{refl['log_likelihood_per_return']:.4f} nats/return, one global histogram "
            f"{refl['baseline_per_return']:.4f} (gain {refl['gain_per_return']:+.4f})"
        )
    return lines


def nonfinite_reason(row: dict[str, Any]) -> str | None:
    """Why a model's printed scores are not finite numbers, or None when they are."""
    numbers = ("log_likelihood_per_ray", "log_density_per_ray", "log_loss_per_event", "ece")
    if all(math.isfinite(row[k]) for k in numbers if k in row):
        return None
    if row.get("impossible_events"):
        return (
            f"log-likelihood -inf: {row['impossible_events']:,} scored event(s) had "
            "probability 0 under this model (an outcome it rules out), so the held-out "
            "rays are infinitely unlikely"
        )
    return "a score is not a finite number: the events' statistics hold NaN or Inf"


# --- fitting the prior (empirical Bayes) -------------------------------------------------------


def sample_log_likelihood(
    arrays: tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_], FloatArray],
    shape: float,
    rate: float,
    gradient: bool = False,
) -> tuple[float, FloatArray]:
    """Weighted log-likelihood of the sampled events under Gamma(shape, rate), and its
    gradient with respect to (log shape, log rate) when asked."""
    s, n, chord, hit, w = arrays
    x = chord / (s + rate)
    log1p_x = np.log1p(x)
    log_q = -(n + shape) * log1p_x  # log P(pass)
    with np.errstate(divide="ignore"):
        log_p = np.where(hit, np.log(-np.expm1(log_q)), log_q)
    total = float(np.dot(w, log_p))
    if not gradient:
        return total, np.zeros(2)
    # d log q / d shape, d log q / d rate
    dq_shape = -log1p_x
    dq_rate = (n + shape) * chord / ((s + rate) * (s + rate + chord))
    q = np.exp(log_q)
    with np.errstate(divide="ignore", invalid="ignore"):
        factor = np.where(hit, -q / (-np.expm1(log_q)), 1.0)
    g_shape = float(np.dot(w, factor * dq_shape)) * shape
    g_rate = float(np.dot(w, factor * dq_rate)) * rate
    return total, np.array([g_shape, g_rate])


@dataclass
class FittedPrior:
    shape: float
    rate: float
    log_likelihood_per_ray: float
    uniform_log_likelihood_per_ray: float
    rays: int
    events: int

    @property
    def gain(self) -> float:
        """Relative improvement of the held-out log-likelihood per ray over the uniform
        prior (0.3: 30% less negative)."""
        base = self.uniform_log_likelihood_per_ray
        return (self.log_likelihood_per_ray - base) / abs(base) if base else 0.0

    @property
    def prior(self) -> Prior:
        return Prior(self.shape, self.rate)

    def json(self) -> dict[str, Any]:
        return {
            "shape": self.shape,
            "rate": self.rate,
            "gain": self.gain,
            "log_likelihood_per_ray": self.log_likelihood_per_ray,
            "uniform_log_likelihood_per_ray": self.uniform_log_likelihood_per_ray,
            "rays": self.rays,
            "events_sampled": self.events,
        }

    def parameter_snippet(self) -> str:
        return (
            "/**:\n  ros__parameters:\n"
            f"    prior.shape: {self.shape:.6g}\n    prior.rate: {self.rate:.6g}\n"
        )


GRID_SHAPES = (0.01, 0.03, 0.1, 0.3, 1.0, 3.0)
GRID_RATES = (0.001, 0.003, 0.01, 0.03, 0.1, 0.3, 1.0)


def fit_prior(sample: EventSample) -> FittedPrior:
    """The Gamma prior of largest held-out likelihood of the sampled events: a coarse grid,
    then L-BFGS on (log shape, log rate) with the exact gradient."""
    from scipy.optimize import minimize

    arrays = sample.arrays()
    rays = max(sample.rays, 1)
    if arrays[0].size == 0:
        raise ValueError("nothing to fit: no held-out ray was scored")
    if not arrays[3].any():
        raise ValueError(
            f"nothing to fit: none of the {sample.rays:,} held-out rays has a return (all "
            "cut at max_range or flagged no-return?); a prior needs returns to be fitted"
        )
    if not np.all(np.isfinite(arrays[0])) or not np.all(np.isfinite(arrays[1])):
        raise ValueError("the fit failed: the held-out events' statistics hold NaN or Inf")
    grid = [(sample_log_likelihood(arrays, a, b)[0], a, b) for a in GRID_SHAPES for b in GRID_RATES]
    grid_best, a0, b0 = max(grid)

    def loss(x: FloatArray) -> tuple[float, FloatArray]:
        value, grad = sample_log_likelihood(arrays, math.exp(x[0]), math.exp(x[1]), True)
        return -value / rays, -grad / rays

    best = minimize(
        loss,
        np.log([a0, b0]),
        jac=True,
        method="L-BFGS-B",
        bounds=[(math.log(1e-6), math.log(1e6))] * 2,
    )
    shape, rate = (float(math.exp(v)) for v in best.x)
    fitted = sample_log_likelihood(arrays, shape, rate)[0] / rays
    uniform = sample_log_likelihood(arrays, UNIFORM.shape, UNIFORM.rate)[0] / rays
    at_bound = any(abs(abs(v) - math.log(1e6)) < 1e-6 for v in best.x)
    # L-BFGS may stop short of its tolerance (a line search) at a good point: only a
    # non-finite result, one at the bounds, or one worse than the grid's best is a failure
    worse = fitted < grid_best / rays - 1e-9 * abs(grid_best / rays)
    if not math.isfinite(fitted) or at_bound or worse:
        raise ValueError(
            f"the fit failed ({best.message}; shape {shape:.3g}, rate {rate:.3g} m, held-out "
            f"log-likelihood per ray {fitted:.6g}): the held-out events do not determine a "
            "prior (too few returns, or a score of -inf)"
        )
    return FittedPrior(shape, rate, fitted, uniform, sample.rays, int(arrays[0].size))


# --- the family of priors that scales with the voxel: shape a * resolution, rate a * res / 2 ----


@dataclass
class RecordingSample:
    """The held-out events that ``fit-prior`` sampled from one recording at one resolution."""

    recording: str
    resolution: float
    sample: EventSample

    def per_ray(self, prior: Prior) -> float:
        """The sample's log-likelihood per ray under ``prior``."""
        arrays = self.sample.arrays()
        return sample_log_likelihood(arrays, prior.shape, prior.rate)[0] / max(self.sample.rays, 1)


SCALE_GRID = tuple(10.0 ** (k / 4.0) for k in range(-20, 9))
"""The coarse grid of ``fit_scale`` (1e-5 to 100 per metre), before a bounded search."""


def fit_scale(samples: list[RecordingSample]) -> float:
    """The family's ``scale`` (per metre) of largest held-out log-likelihood: the sum over
    ``samples`` of each one's log-likelihood PER RAY, so every recording and resolution
    weighs the same whatever its size. ValueError when there is nothing to fit."""
    from scipy.optimize import minimize_scalar

    if not samples:
        raise ValueError("nothing to fit: no recording")
    cached = [(r.sample.arrays(), max(r.sample.rays, 1), r.resolution) for r in samples]
    for r, (arrays, _, _) in zip(samples, cached, strict=True):
        if not arrays[3].any():
            raise ValueError(
                f"nothing to fit: {r.recording} at {r.resolution:g} m has no held-out return"
            )

    def loss(log_scale: float) -> float:
        a = math.exp(log_scale)
        return -sum(
            sample_log_likelihood(arrays, a * res, a * res / 2.0)[0] / rays
            for arrays, rays, res in cached
        )

    start = min(SCALE_GRID, key=lambda a: loss(math.log(a)))
    step = math.log(10.0) / 4.0
    low, high = math.log(start) - step, math.log(start) + step
    best = minimize_scalar(loss, bounds=(low, high), method="bounded", options={"xatol": 1e-6})
    scale = float(math.exp(best.x))
    edge = start in (SCALE_GRID[0], SCALE_GRID[-1])
    if not math.isfinite(best.fun) or edge:
        raise ValueError(
            f"the fit of the family's scale failed (best {scale:.3g} per metre, at the edge of "
            f"{SCALE_GRID[0]:g}..{SCALE_GRID[-1]:g} or a score of -inf)"
        )
    return scale


@dataclass
class HeldOutRow:
    """One recording at one resolution, scored with the family's scale fitted WITHOUT it."""

    recording: str
    resolution: float
    scale: float
    """The scale fitted on the other recordings."""
    family: float
    """Log-likelihood per ray with ``family_prior(scale, resolution)``."""
    own: float
    """... with the two-parameter prior fitted on this recording at this resolution."""
    own_prior: Prior
    uniform: float
    """... with the uniform prior."""

    @property
    def gap(self) -> float:
        """How much worse the held-out family is than the recording's own fit (0.05: 5%)."""
        return (self.own - self.family) / abs(self.own) if self.own else 0.0

    def json(self) -> dict[str, Any]:
        return {
            "recording": self.recording, "resolution": self.resolution, "scale": self.scale,
            "log_likelihood_per_ray": self.family, "own_log_likelihood_per_ray": self.own,
            "own_prior": _prior_json(self.own_prior),
            "uniform_log_likelihood_per_ray": self.uniform, "gap_to_own": self.gap,
        }  # fmt: skip


def leave_one_out(samples: list[RecordingSample], own: dict[int, Prior]) -> list[HeldOutRow]:
    """For every recording: the scale fitted on the others, scored on it at each resolution,
    beside its own fitted prior (``own[k]``: the prior fitted on ``samples[k]``) and the
    uniform prior. Needs two recordings or more."""
    names = list(dict.fromkeys(r.recording for r in samples))
    if len(names) < 2:
        raise ValueError("leave-one-recording-out needs two recordings or more")
    rows = []
    for name in names:
        scale = fit_scale([r for r in samples if r.recording != name])
        for k, r in enumerate(samples):
            if r.recording != name:
                continue
            rows.append(HeldOutRow(
                name, r.resolution, scale, r.per_ray(family_prior(scale, r.resolution)),
                r.per_ray(own[k]), own[k], r.per_ray(UNIFORM),
            ))  # fmt: skip
    return rows


# --- the reliability diagram ------------------------------------------------------------------


def plot_reliability(report_: dict[str, Any], path: str | Path, title: str = "") -> Path:
    """The reliability diagram (observed frequency against mean predicted probability, on
    log-spaced bins) of every model of the report, with the events per bin below."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    models = [("this model", report_)] + [
        (k, v) for k, v in report_.items() if isinstance(v, dict) and "calibration_log" in v
    ]
    fig, (top, bottom) = plt.subplots(
        2, 1, figsize=(6.4, 7.2), gridspec_kw={"height_ratios": [3, 1]}, sharex=True
    )
    floor = 1e-6
    top.plot([floor, 1], [floor, 1], color="0.6", lw=1, ls="--", label="perfect calibration")
    for name, r in models:
        rows = r["calibration_log"]
        x = [max(row["mean_predicted"], floor) for row in rows]
        y = [max(row["observed_frequency"], floor) for row in rows]
        what = name
        if "prior" in r:
            what += f" (prior {r['prior']['shape']:.3g}, {r['prior']['rate']:.3g})"
        label = f"{what}: {r['log_likelihood_per_ray']:.2f} nats/ray, ECE {r['ece']:.4f}"
        top.plot(x, y, marker="o", ms=3, label=label)
        bottom.plot(x, [row["count"] for row in rows], marker="o", ms=3)
    top.set_xscale("log")
    top.set_yscale("log")
    top.set_ylabel("observed frequency of a return")
    top.legend(fontsize=7, loc="upper left")
    top.set_title(title or "held-out rays: predicted vs observed returns", fontsize=9)
    bottom.set_yscale("log")
    bottom.set_xlabel("predicted probability of a return in the voxel")
    bottom.set_ylabel("events")
    fig.tight_layout()
    out = Path(path)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


# --- running a split ---------------------------------------------------------------------------

SPLITS = ("even-odd", "shots")


def run_input(
    recording: Recording,
    opts: Any,
    consume: Callable[[Mapper, PlacedScan], IntegrationSummary],
    progress: bool,
    log: Callable[[str], None] | None,
) -> Any:
    """Replay ``recording`` with ``consume`` doing the work; the ``ReplayResult`` (its
    mapper holds what ``consume`` integrated into it)."""
    from mfp_mapper.mapping.replay import replay

    return replay(recording, opts, progress, log, consume=consume)


def split_options(
    opts: Any, split: str, within_training: bool = False
) -> tuple[Any, Any, slice | None, slice | None]:
    """(training options, held-out options, training rays, held-out rays) of a split:
    ``even-odd``: of the scans selected, the 1st, 3rd... build the map and the 2nd, 4th...
    are scored; ``shots``: within every scan, the even rays build the map, the odd ones are
    scored. ``within_training``: the same split of the training part alone (scans or rays
    0, 4, 8... build the map, 2, 6, 10... are held out), for ``fit-prior``: what ``score``
    later holds out is never used."""
    k = 2 if within_training else 1
    if split == "even-odd":
        step = opts.replay.every * k
        train = opts.but(every=2 * step)
        held = opts.but(every=2 * step, start_index=opts.replay.start_index + step)
        return train, held, None, None
    if split == "shots":
        return opts, opts, slice(0, None, 2 * k), slice(k, None, 2 * k)
    raise ValueError(f"unknown split {split!r}: {', '.join(SPLITS)}")


def score_split(
    recording: Recording,
    opts: Any,
    split: str,
    priors: dict[str, Prior],
    *,
    classic: bool = True,
    sample: EventSample | None = None,
    within_training: bool = False,
    progress: bool = False,
    log: Callable[[str], None] | None = None,
) -> Scorer:
    """Build the map (and classic occupancy) from the training part of ``recording``, score
    the held-out part with ``Scorer`` (``within_training``: see ``split_options``)."""
    train_opts, held_opts, train_rays, held_rays = split_options(opts, split, within_training)
    classic_map = ClassicMap() if classic else None
    echo_maps = EchoMaps()
    trained = run_input(
        recording, train_opts, training_consumer(classic_map, train_rays, echo_maps), progress, log
    )
    scorer = Scorer(trained.mapper, priors, classic_map, sample, held_rays)
    if echo_maps.maps:
        scorer.echoes = EchoScores(echo_maps)
    run_input(recording, held_opts, scorer, progress, log)
    return scorer


def score_map(
    mapper: Mapper,
    recordings: list[Recording],
    opts: Any,
    priors: dict[str, Prior],
    *,
    progress: bool = False,
    log: Callable[[str], None] | None = None,
) -> Scorer:
    """Score every selected scan of ``recordings`` against a given map (no classic
    occupancy: its training rays are not in a map file)."""
    scorer = Scorer(mapper, priors)
    for recording in recordings:
        run_input(recording, opts, scorer, progress, log)
    return scorer


def scored_keys() -> Iterable[str]:
    """The keys every model's report has."""
    return (
        "rays", "events", "log_likelihood_per_ray", "log_loss_per_event", "brier", "ece",
        "calibration",
    )  # fmt: skip
