"""Frame sources of the publisher (docs/design.md §2 data flow, §6, §7).

A source yields :class:`Item` s: the wire payload of one ``RFFrame`` (the bytes that go on
``fp/<rig>/rf``), its header (the zenoh attachment) and its time in the source's own clock
(``t_s``: acquisition timestamp, or the MCAP log time on replay) for "original timing" pacing.

* :class:`SimulatorSource` — ``fpcore.simulate`` scenarios (the embedded default); it also offers
  the calibration acquisitions of the scenario's targets (:meth:`SimulatorSource.fingerprint_specs`).
* :class:`AcquisitionSource` — any iterable of ``fpcore.Acquisition`` (tests use ``fpcore.born``).
* :class:`UFFSource` — frames of a UFF file (``fpcore.io.read_uff``).
* :class:`MCAPSource` — the ``…/rf`` messages of a recording, the same bytes, the recorded log times.
* :class:`IngestSource` — whatever any program puts on ``fp/<rig>/ingest``; items are marked
  ``trusted=False`` so the publisher validates them before forwarding (docs/design.md §7 bad input).

Sources are plain iterables; ``repeat`` replays a finite source several times with increasing frame
indices (benchmarks).
"""

from __future__ import annotations

import dataclasses
import queue
import threading
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from services.messages import RFFrame
from services.recording import iter_recording, topic_counts
from services.registry import FingerprintSpec
from services.topics import keys, parse_key
from services.wire import decode_header, encode_with_header, extract_header

if TYPE_CHECKING:  # pragma: no cover
    import zenoh

    from fpcore.acquisition import Acquisition
    from fpcore.simulate import Scenario

__all__ = [
    "AcquisitionSource",
    "IngestSource",
    "Item",
    "MCAPSource",
    "SimulatorSource",
    "Source",
    "UFFSource",
    "born_frames",
    "frame_item",
]


@dataclass
class Item:
    """One frame to publish: payload bytes, header bytes (attachment), frame index, source time (s)."""

    payload: bytes
    header: bytes
    frame_index: int | None
    t_s: float
    trusted: bool = True


class Source(Protocol):
    """What the publisher reads: an iterable of items, optionally bound to a zenoh session."""

    def __iter__(self) -> Iterator[Item]: ...


def frame_item(acq: Acquisition, frame_index: int | None = None) -> Item:
    """Encode an acquisition as an RFFrame item (frame index overridden if given)."""
    if frame_index is not None and frame_index != acq.frame_index:
        acq = dataclasses.replace(acq, frame_index=frame_index)
    payload, header = encode_with_header(RFFrame.from_acquisition(acq))
    return Item(payload, header, acq.frame_index, float(acq.timestamp))


class AcquisitionSource:
    """Frames from an iterable of acquisitions; ``repeat`` > 1 cycles a finite list (new frame indices,
    timestamps shifted by the list's duration + one frame period)."""

    def __init__(self, frames: Iterable[Acquisition], repeat: int = 1, limit: int | None = None) -> None:
        self._frames = frames
        self.repeat = repeat
        self.limit = limit

    def __iter__(self) -> Iterator[Item]:
        if self.repeat == 1:
            it: Iterator[Acquisition] = iter(self._frames)
            for n, acq in enumerate(it):
                if self.limit is not None and n >= self.limit:
                    return
                yield frame_item(acq)
            return
        frames = list(self._frames)
        if not frames:
            return
        ts = [f.timestamp for f in frames]
        period = (ts[-1] - ts[0]) / (len(ts) - 1) if len(ts) > 1 and ts[-1] > ts[0] else 0.1
        span = ts[-1] - ts[0] + period
        n = 0
        for r in range(self.repeat):
            for acq in frames:
                if self.limit is not None and n >= self.limit:
                    return
                acq2 = dataclasses.replace(acq, frame_index=n, timestamp=acq.timestamp + r * span)
                yield frame_item(acq2)
                n += 1


class SimulatorSource(AcquisitionSource):
    """Frames of an ``fpcore.simulate`` scenario, e.g. ``SimulatorSource("sinking-sphere", quick=True)``.

    ``cache=True`` keeps the generated acquisitions so that ``repeat`` and a second pass cost nothing
    (the simulator is exact, not fast: seconds per 3D frame).
    """

    def __init__(
        self,
        scenario: str | Scenario,
        n_frames: int | None = None,
        quick: bool = True,
        seed: int = 0,
        repeat: int = 1,
        cache: bool = True,
        **kwargs: Any,
    ) -> None:
        from fpcore import simulate

        sc = simulate.scenario(scenario, quick=quick, seed=seed, **kwargs) if isinstance(scenario, str) else scenario
        self.scenario = sc
        self.n_frames = sc.n_frames if n_frames is None else min(int(n_frames), sc.n_frames)
        self._cache: list[Acquisition] | None = [] if cache else None
        super().__init__(self._generate(), repeat=repeat)

    def _generate(self) -> Iterable[Acquisition]:
        outer = self

        class _Frames:
            def __iter__(self) -> Iterator[Acquisition]:
                cache = outer._cache
                if cache is not None and len(cache) >= outer.n_frames:
                    yield from cache[: outer.n_frames]
                    return
                for i in range(outer.n_frames):
                    if cache is not None and i < len(cache):
                        yield cache[i]
                        continue
                    acq = outer.scenario.frame(i)
                    if cache is not None:
                        cache.append(acq)
                    yield acq

        return _Frames()

    @property
    def band(self) -> tuple[float, float]:
        return self.scenario.band

    def fingerprint_specs(self, targets: list[str] | None = None) -> list[FingerprintSpec]:
        """Calibration specs of the scenario's targets (target alone in water at its r0)."""
        out = []
        for name in targets or self.scenario.target_names:
            cal = self.scenario.calibration(name)
            truth = cal.ground_truth
            x, y, z = truth.r0  # a simulated calibration records where its target is
            out.append(
                FingerprintSpec(
                    name, calibration=cal, r0=(float(x), float(y), float(z)), diameter=float(truth.diameter_m or 0.0)
                )
            )
        return out


class UFFSource(AcquisitionSource):
    """Frames of a UFF file (``fpcore.io.read_uff``; docs/design.md §3 exchange format)."""

    def __init__(self, path: str | Path, dataset: str | None = None, repeat: int = 1) -> None:
        from fpcore.io import read_uff

        self.path = Path(path)
        super().__init__(read_uff(self.path, dataset), repeat=repeat)


def _is_rf(key: str, rig: str | None) -> bool:
    try:
        r, topic = parse_key(key)
    except ValueError:
        return False
    return topic == "rf" and (rig is None or r == rig)


class MCAPSource:
    """The ``…/rf`` messages of a recording (same bytes), with their log times for original timing.

    ``from_rig`` selects the recorded rig (default: any). Bad frames in the recording are replayed
    as they were (the processor refuses them again).
    """

    def __init__(self, path: str | Path, from_rig: str | None = None, repeat: int = 1) -> None:
        self.path = Path(path)
        self.from_rig = from_rig
        self.repeat = repeat
        if not self.path.is_file():
            raise FileNotFoundError(f"{self.path}: no such recording")
        rf = {k: n for k, n in topic_counts(self.path).items() if _is_rf(k, from_rig)}
        if not rf:
            which = f"fp/{from_rig}/rf" if from_rig else "fp/<rig>/rf"
            raise ValueError(
                f"--mcap: {self.path} holds no RF frames ({which} messages) to replay; record with the rf "
                "topic included (`fp record` keeps it unless --exclude leaves it out)"
            )
        self.frames = sum(rf.values())

    def __iter__(self) -> Iterator[Item]:
        for _ in range(self.repeat):
            t_first: int | None = None
            for key, payload, log_ns, _pub in iter_recording(self.path):
                try:
                    rig, topic = parse_key(key)
                except ValueError:
                    continue
                if topic != "rf" or (self.from_rig is not None and rig != self.from_rig):
                    continue
                t_first = log_ns if t_first is None else t_first
                try:
                    header = extract_header(payload)
                    frame_index = decode_header(header, strict=False).frame_index
                except Exception:  # a raw bad message is replayed as recorded
                    header, frame_index = b"", None
                yield Item(payload, header, frame_index, (log_ns - t_first) * 1e-9)


class IngestSource:
    """Frames any program puts on ``fp/<rig>/ingest`` (raw RFFrame payloads); live, unbounded.

    :meth:`bind` subscribes; iteration ends when :meth:`stop` is called. The callback only queues
    (a bounded FIFO, so a flood blocks the producer rather than the node's memory).
    """

    def __init__(self, rig: str, depth: int = 16) -> None:
        self.key = keys(rig).ingest
        self._q: queue.Queue[Item | None] = queue.Queue(maxsize=depth)
        self._stop = threading.Event()
        self._outer = threading.Event()
        self._sub: Any = None

    def bind(self, session: zenoh.Session, stop: threading.Event | None = None) -> None:
        """Subscribe to the ingest key (idempotent); iteration also ends when ``stop`` is set."""
        if stop is not None:
            self._outer = stop
        if self._sub is None:
            self._sub = session.declare_subscriber(self.key, self._on_sample)

    def _on_sample(self, sample: Any) -> None:
        payload = sample.payload.to_bytes()
        att = sample.attachment
        header = att.to_bytes() if att is not None else b""
        while not self._stop.is_set():
            try:
                self._q.put(Item(payload, header, None, 0.0, trusted=False), timeout=0.2)
                return
            except queue.Full:
                continue

    def stop(self) -> None:
        self._stop.set()
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None

    def __iter__(self) -> Iterator[Item]:
        while not (self._stop.is_set() or self._outer.is_set()):
            try:
                item = self._q.get(timeout=0.2)
            except queue.Empty:
                continue
            if item is not None:
                yield item


def born_frames(
    n_frames: int,
    n_elements: int = 32,
    n_waves: int = 5,
    n_t: int = 400,
    seed: int = 0,
    speckle: int = 60,
    t0: float = 10e-6,
) -> tuple[list[Acquisition], Acquisition]:
    """Small 2D frames for tests and quick runs (``fpcore.born``, single scattering): a point-cluster
    target moving through Born speckle, plus its calibration (target alone at r0 = (0, 0, 15 mm));
    truth travels with every frame. 400 samples at 20 MHz from t0 = 10 µs cover z ≈ 8–23 mm."""
    from fpcore import PlaneWaveSequence, Probe
    from fpcore.born import born_points

    rng = np.random.default_rng(seed)
    probe = Probe.linear(n_elements, 0.3e-3, 2.5e6, 1.5e6)
    seq = PlaneWaveSequence.from_angles(np.linspace(-10, 10, n_waves))
    offs = rng.uniform(-0.8e-3, 0.8e-3, (6, 3))
    offs[:, 1] = 0.0
    amps = rng.uniform(0.6, 1.0, 6)
    r0 = np.array([0.0, 0.0, 15e-3])
    cal = born_points(probe, seq, r0 + offs, amps, n_t=n_t, t0=t0)
    cal.truth = {
        "targets": [{"name": "marker", "position_m": r0.tolist(), "diameter_m": 1.6e-3}],
        "r0_m": r0.tolist(),
        "diameter_m": 1.6e-3,
    }
    sp = np.stack([rng.uniform(-6e-3, 6e-3, speckle), np.zeros(speckle), rng.uniform(10e-3, 22e-3, speckle)], 1)
    sp_amp = 0.3 * rng.standard_normal(speckle)
    frames = []
    for k in range(n_frames):
        t = np.array([-1e-3 + 0.2e-3 * k, 0.0, 14e-3 + 0.3e-3 * k])
        acq = born_points(
            probe,
            seq,
            np.concatenate([t + offs, sp]),
            np.concatenate([amps, sp_amp]),
            n_t=n_t,
            t0=t0,
            frame_index=k,
            timestamp=0.1 * k,
        )
        acq.truth = {"targets": [{"name": "marker", "position_m": t.tolist()}]}
        frames.append(acq)
    return frames, cal
