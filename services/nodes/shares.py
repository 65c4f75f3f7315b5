"""A sharded processor's shares and dictionary front (docs/scaling.md; used by ``services.nodes.merger``).

Shares. A frame's work is a list of *units*: ``*`` (the whole frame, ``--shard frame``) or, in the
fingerprint modes, one unit per dictionary entry plus ``@image`` (the confocal image and the truth report,
``services.nodes.worker.IMAGE_UNIT``). :func:`split_units` deals a frame's units over its target workers in
turn, starting at an offset that rotates with the frame index: shares differ by at most one unit and the
extra unit moves from frame to frame. :func:`worker_groups` cuts the live workers (sorted by name) into
groups for ``--shard both``. :func:`join_parts` turns the parts of one frame into the one result the
single node would have given: [truth report,] image, γ-maps in dictionary order, then one Detections with
the detections of every fingerprint in dictionary order (each fingerprint's in its worker's order), as
``services.pipeline.Pipeline.process`` orders them.

Dictionary front. Every worker serves the dictionary protocol (``services.registry``) for itself on
``fp/<rig>/@shard/assign/<worker>/dictionary/**``; :class:`DictionaryFront` answers the rig's
``fp/<rig>/dictionary/**`` for the whole deployment: ``list`` is the union of the live workers' entries
(with each worker's names under ``workers``), ``<name>`` is answered by the first live worker that holds
it, and ``add``, ``remove`` and ``set`` are sent to every live worker (each holds the whole dictionary) and
answered ``ok`` only when every worker accepted (otherwise the first refusal, and ``workers`` says which
accepted). After a change, and when a worker joins, the front reads the dictionary back and hands the
names, in order, to the merger (``on_names(worker, names, changed)``) for the next frames' shares.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
from collections.abc import Callable
from typing import Any

import zenoh

from services.messages import Detections
from services.nodes.worker import IMAGE_UNIT, ShardResult, worker_dictionary_root
from services.topics import Keys
from services.wire import decode, decode_header, encode, extract_header

__all__ = ["DictionaryFront", "join_parts", "split_units", "worker_groups"]

log = logging.getLogger("fp.merger")
ASK_TIMEOUT_S = 60.0  # an add with a calibration builds it on every worker


def split_units(units: list[str], targets: list[str], frame_index: int) -> dict[str, list[str]]:
    """worker → its units: unit i goes to ``targets[(i + frame_index) % len(targets)]`` (module doc)."""
    out: dict[str, list[str]] = {}
    for i, u in enumerate(units):
        out.setdefault(targets[(i + frame_index) % len(targets)], []).append(u)
    return out


def worker_groups(members: list[str], size: int) -> list[list[str]]:
    """The live workers (sorted) cut into groups of ``size``; a last, smaller group joins the one before it
    when it would be alone (so that every group splits the dictionary)."""
    ms = sorted(members)
    groups = [ms[i : i + size] for i in range(0, len(ms), size)]
    if len(groups) > 1 and len(groups[-1]) < size and size > 1 and len(groups[-1]) == 1:
        groups[-2].extend(groups.pop())
    return groups


def join_parts(frame_index: int, units: list[str], got: dict[str, ShardResult]) -> ShardResult:
    """The one result of a frame from its parts (``got``: unit → the part that covered it; module doc)."""
    parts = list({id(r): r for r in (got[u] for u in units)}.values())
    own = got.get(IMAGE_UNIT, parts[0])
    names = [u for u in units if u != IMAGE_UNIT]
    gammas: dict[str, bytes] = {}
    dets: dict[str, list[Any]] = {n: [] for n in names}
    base: Detections | None = None
    for r in parts:
        for topic, p in r.messages:
            if topic == "gamma":
                gammas[str(decode_header(extract_header(p)).fields.get("fingerprint"))] = p
            elif topic == "detections":
                d = decode(p, expect=Detections)
                assert isinstance(d, Detections)
                base = base or d
                for det in d.detections:
                    dets.setdefault(det.fingerprint, []).append(det)
    msgs = [(t, p) for t, p in own.messages if t in ("errors", "image")]
    msgs += [("gamma", gammas[n]) for n in names if n in gammas]
    merged = [d for n in dets for d in dets[n]]  # dictionary order, then any other name as it came
    if base is not None:
        msgs.append(("detections", encode(base.model_copy(update={"detections": merged}))))
    nulls = {n: nm for r in parts for n, nm in r.nulls.items()}
    return ShardResult(
        frame_index,
        own.timestamp,
        ",".join(sorted({r.worker for r in parts})),
        "result",
        msgs,
        {n: nulls[n] for n in names if n in nulls},
        own.tracker,
        own.grid,
        sum(r.compute_s for r in parts),
        list(units),
    )


def _json(z: Any) -> dict[str, Any]:
    try:
        doc = json.loads(z.payload.to_bytes())
    except (ValueError, UnicodeDecodeError):
        return {"ok": False, "error": "a reply that is not JSON"}
    return doc if isinstance(doc, dict) else {"ok": False, "error": "a reply that is not a JSON object"}


class DictionaryFront:
    """``fp/<rig>/dictionary/**`` of a sharded deployment, answered from its workers on a thread (module doc)."""

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        workers: Callable[[], list[str]],
        on_names: Callable[[str, list[str], bool], None],
        name: str = "merger-dict",
    ) -> None:
        self.session, self.keys, self.workers, self.on_names, self.name = session, keys, workers, on_names, name
        self._jobs: queue.Queue[Any] = queue.Queue()
        self._thread: threading.Thread | None = None
        self._queryable: Any = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self._serve, name=self.name, daemon=True)
        self._thread.start()
        self._queryable = self.session.declare_queryable(self.keys.dictionary, self._jobs.put)

    def stop(self, timeout: float = 30) -> None:
        if self._queryable is not None:
            self._queryable.undeclare()
            self._queryable = None
        self._jobs.put(None)
        if self._thread is not None:
            self._thread.join(timeout=timeout)

    def refresh(self, worker: str) -> None:
        """Read ``worker``'s dictionary (it joined) and hand its names to ``on_names`` (on the front's thread)."""
        self._jobs.put(("refresh", worker))

    # -- the thread -------------------------------------------------------------------------------------
    def _serve(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            try:
                if isinstance(job, tuple):
                    self._refresh(job[1])
                else:
                    self._answer(job)
            except Exception as exc:  # a bad request never takes the node down
                log.error("dictionary: %s", exc)
            del job  # finalises a query

    def _ask(self, workers: list[str], suffix: str, payload: bytes | None = None, att: bytes | None = None) -> dict:
        """worker → its JSON reply to ``<its dictionary root><suffix>`` (asked of all at once)."""
        handlers = {}
        for w in workers:
            key = worker_dictionary_root(self.keys, w) + suffix
            handlers[w] = self.session.get(key, payload=payload, attachment=att, timeout=ASK_TIMEOUT_S)
        out: dict[str, dict[str, Any]] = {}
        for w, h in handlers.items():
            for reply in h:
                out[w] = _json(reply.ok if reply.ok is not None else reply.err)
                break
            else:
                out[w] = {"ok": False, "error": f"no reply from worker {w}"}
        return out

    def _refresh(self, worker: str, changed: bool = False, tries: int = 3) -> None:
        for _ in range(tries):
            doc = self._ask([worker], "/list").get(worker, {})
            if doc.get("ok"):
                self.on_names(worker, [str(e["name"]) for e in doc.get("entries", [])], changed)
                return
        log.warning("could not read worker %s's dictionary: %s", worker, doc.get("error"))

    def _answer(self, query: Any) -> None:
        key = str(query.key_expr)
        parts = self.keys.dictionary_path(key)
        op = parts[0] if parts else "list"
        workers = self.workers()
        reply_key = key
        if not workers:
            ok, doc = (
                False,
                {"ok": False, "error": "no γ worker alive: the dictionary lives on the workers (fp worker)"},
            )
        elif op in ("list", "**", "*") or any("*" in p for p in parts):
            ok, doc = self._union(self._ask(workers, "/list"))
            reply_key = self.keys.dictionary_op("list") if "*" in key else key
        elif op in ("add", "remove", "set"):
            suffix = key[len(self.keys.dictionary_root) :]
            payload = None if query.payload is None else query.payload.to_bytes()
            att = None if query.attachment is None else query.attachment.to_bytes()
            replies = self._ask(workers, suffix, payload, att)
            ok = all(r.get("ok") for r in replies.values())
            first = next((r for r in replies.values() if r.get("ok") == ok), {"ok": False})
            doc = {**first, "workers": {w: bool(r.get("ok")) for w, r in replies.items()}}
            if not ok:
                doc["error"] = "; ".join(f"{w}: {r.get('error')}" for w, r in replies.items() if not r.get("ok"))
            for w in workers[:1]:
                self._refresh(w, changed=True)
        else:
            replies = self._ask(workers, "/" + "/".join(parts))
            found = [r for r in replies.values() if r.get("ok")]
            ok, doc = bool(found), found[0] if found else next(iter(replies.values()))
        body = json.dumps(doc).encode()
        if ok:
            query.reply(reply_key, body)
        else:
            query.reply_err(body)

    @staticmethod
    def _union(replies: dict[str, dict[str, Any]]) -> tuple[bool, dict[str, Any]]:
        good = {w: r for w, r in replies.items() if r.get("ok")}
        if not good:
            return False, {"ok": False, "error": "; ".join(f"{w}: {r.get('error')}" for w, r in replies.items())}
        entries: dict[str, Any] = {}
        for r in good.values():
            for e in r.get("entries", []):
                entries.setdefault(str(e["name"]), e)
        first = next(iter(good.values()))
        per_worker = {w: [str(e["name"]) for e in r.get("entries", [])] for w, r in replies.items()}
        return True, {
            "ok": True,
            "params": first.get("params"),
            "entries": list(entries.values()),
            "workers": per_worker,
        }
