"""Key expressions of the bus, all generated from one table (docs/design.md §2, §7).

Every key is ``fp/<rig>/<chunk>``. :data:`TABLE` names each chunk, the message schema published there
(None for queryables and liveliness tokens) and its use; :class:`Keys` (``keys(rig)``) builds the
keys of one rig from it, so no node, test or benchmark writes a key by hand:

* data topics: ``rf``, ``ingest``, ``gamma``, ``image``, ``detections``, ``tracks``, ``status``, ``errors``;
* the acknowledgements that pace a replaying publisher: ``detections`` and ``errors`` (:attr:`Keys.acks`);
* the dictionary queryable ``dictionary/**`` and its operations ``dictionary/{list,add/<name>,
  remove/<name>,set,<name>}`` (:meth:`Keys.dictionary_op`);
* sharded processing (docs/scaling.md): ``@shard/assign/<worker>`` and ``@shard/result``, verbatim chunks
  that ``**`` does not match (a recorder of ``fp/<rig>/**`` leaves them out);
* liveliness tokens ``alive/<role>[/<name>]`` (:meth:`Keys.alive`; :meth:`Keys.alive_any` matches any
  name of a role);
* every node's barrier queryable ``@sync/<role>[/<name>]`` (:meth:`Keys.sync`, :meth:`Keys.sync_any`): its
  reply comes after the node has taken every message the asker sent it before (one link, in order);
* ``**``: everything of the rig (what the recorder subscribes to); :data:`ALL_RIGS` is ``fp/**``.

Rig ``"*"`` gives wildcard keys (``keys("*").rf == "fp/*/rf"``). Pure: no zenoh.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any, NamedTuple

__all__ = ["ALL_RIGS", "DICTIONARY_OPS", "PREFIX", "TABLE", "TOPICS", "Keys", "Topic", "keys", "parse_key", "sync_of"]

PREFIX = "fp"
ALL_RIGS = f"{PREFIX}/**"


class Topic(NamedTuple):
    chunk: str  # the key under fp/<rig>/
    schema: str | None  # message schema published there (None: queryable, token, wildcard)
    use: str


#: name → key chunk under ``fp/<rig>/``, schema and use: the one table every key comes from.
TABLE: dict[str, Topic] = {
    "rf": Topic("rf", "RFFrame", "RF frames, publisher → processor and recorder"),
    "gamma": Topic("gamma", "GammaMap", "one γ-map per fingerprint and frame"),
    "image": Topic("image", "ConfocalImage", "confocal image per frame"),
    "detections": Topic("detections", "Detections", "detections per frame (also the frame's acknowledgement)"),
    "tracks": Topic("tracks", "Tracks", "active tracks per frame"),
    "status": Topic("status", "Status", "periodic node status"),
    "errors": Topic("errors", "ErrorReport", "refused inputs (also acknowledge the frame they name)"),
    "ingest": Topic("ingest", None, "untrusted RFFrame payloads from any program, validated by the publisher"),
    "dictionary": Topic("dictionary", None, "queryable of the processor's fingerprint dictionary"),
    "alive": Topic("alive", None, "liveliness tokens alive/<role>[/<name>]"),
    "sync": Topic("@sync", None, "barrier queryable of every node: @sync/<role>[/<name>] (services.bus.sync_with)"),
    # Sharded processing (docs/scaling.md): '@' chunks are verbatim, so ``fp/<rig>/**`` (a recorder) never sees them.
    "shard_assign": Topic("@shard/assign", None, "merger → one γ worker: the RFFrame it computes, as it came"),
    "shard_result": Topic("@shard/result", None, "γ worker → merger: one frame's results (services.nodes.worker)"),
    "all": Topic("**", None, "everything of the rig"),
}

#: topic (last key chunk) → schema name published there.
TOPICS: dict[str, str] = {t.chunk: t.schema for t in TABLE.values() if t.schema is not None}
#: dictionary operations with a fixed key (``add`` and ``remove`` take a name, ``get`` is the name itself).
DICTIONARY_OPS = ("list", "get", "add", "remove", "set")
_RIG_RE = re.compile(r"^(\*|[A-Za-z0-9_.\-]+)$")
_PLAIN_RE = re.compile(r"^[A-Za-z0-9_.\-]+$")


def _plain_path(name: str, what: str) -> str:
    if not name or any(c in name for c in "*$?#") or name.startswith("/") or name.endswith("/"):
        raise ValueError(f"{what}: expected a plain key chunk path, got {name!r}")
    return name


@dataclass(frozen=True)
class Keys:
    """Key expressions of one rig (``fp/<rig>/...``); rig ``"*"`` gives wildcard subscriptions."""

    rig: str

    def __post_init__(self) -> None:
        if not isinstance(self.rig, str) or not _RIG_RE.match(self.rig):
            raise ValueError(f"rig: expected letters, digits, '_', '-', '.' (or '*'), got {self.rig!r}")

    def _k(self, chunk: str) -> str:
        return f"{PREFIX}/{self.rig}/{chunk}"

    def topic(self, name: str) -> str:
        """Key of a :data:`TABLE` entry, e.g. ``keys("a").topic("gamma") == "fp/a/gamma"``."""
        try:
            return self._k(TABLE[name].chunk)
        except KeyError:
            raise ValueError(f"topic: expected one of {', '.join(TABLE)}, got {name!r}") from None

    def __getattr__(self, name: str) -> Any:  # rf, gamma, image, detections, tracks, status, errors, ingest, all
        if name.startswith("_") or name not in TABLE or name in ("dictionary", "alive"):
            raise AttributeError(name)
        return self.topic(name)

    @property
    def acks(self) -> tuple[str, str]:
        """What acknowledges a frame to a pacing publisher: its Detections, or an ErrorReport naming it."""
        return self.topic("detections"), self.topic("errors")

    # -- dictionary queryable -----------------------------------------------------------------------
    @property
    def dictionary_root(self) -> str:
        """``fp/<rig>/dictionary`` (operations are below it)."""
        return self._k(TABLE["dictionary"].chunk)

    @property
    def dictionary(self) -> str:
        """Queryable of the fingerprint dictionary: ``fp/<rig>/dictionary/**``."""
        return f"{self.dictionary_root}/**"

    def dictionary_entry(self, name: str) -> str:
        """Key of one dictionary entry, ``fp/<rig>/dictionary/<name>``."""
        return f"{self.dictionary_root}/{_plain_path(name, 'name')}"

    def dictionary_op(self, op: str, name: str | None = None) -> str:
        """Key of a dictionary operation: list, get (``…/<name>``), add/remove (``…/<op>/<name>``), set."""
        if op in ("list", "set"):
            return f"{self.dictionary_root}/{op}"
        if op == "get":
            return self.dictionary_entry(name or "")
        if op in ("add", "remove"):
            if not name:
                raise ValueError(f"{op}: a name is required")
            return f"{self.dictionary_root}/{op}/{_plain_path(name, 'name')}"
        raise ValueError(f"op: expected {', '.join(DICTIONARY_OPS[:-1])} or {DICTIONARY_OPS[-1]}, got {op!r}")

    def dictionary_path(self, key: str) -> list[str]:
        """The chunks of a query key below ``fp/<rig>/dictionary`` (empty for the root or another key)."""
        root = self.dictionary_root
        rest = key[len(root) :].lstrip("/") if key.startswith(root) else ""
        return rest.split("/") if rest else []

    # -- liveliness ------------------------------------------------------------------------------------
    def alive(self, role: str, name: str | None = None) -> str:
        """Liveliness token of a node: ``fp/<rig>/alive/<role>``, ``…/<role>/<name>`` when the node's name
        differs from its role (a second processor on the rig)."""
        if not _PLAIN_RE.match(role):
            raise ValueError(f"role: expected a plain key chunk, got {role!r}")
        suffix = "" if name is None or name == role else f"/{_plain_path(name, 'name')}"
        return f"{self._k(TABLE['alive'].chunk)}/{role}{suffix}"

    def alive_any(self, role: str) -> str:
        """Matches every token of a role on the rig, whatever the node's name: ``fp/<rig>/alive/<role>/**``."""
        return f"{self.alive(role)}/**"

    def sync(self, role: str, name: str | None = None) -> str:
        """Barrier queryable of a node, ``fp/<rig>/@sync/<role>[/<name>]`` (named like its token)."""
        return sync_of(self.alive(role, name))

    def sync_any(self, role: str) -> str:
        """Matches the barrier of every node of a role on the rig: ``fp/<rig>/@sync/<role>/**``."""
        return f"{self.sync(role)}/**"

    def shard_assign_to(self, worker: str) -> str:
        """Where the merger assigns frames to one γ worker: ``fp/<rig>/@shard/assign/<worker>``."""
        return f"{self.topic('shard_assign')}/{_plain_path(worker, 'worker')}"

    def for_message(self, msg: Any) -> str:
        """Key a message (or message type) is published on."""
        cls = msg if isinstance(msg, type) else type(msg)
        name = cls.model_fields["schema_name"].default
        topic = next((t for t, s in TOPICS.items() if s == name), None)
        if topic is None:
            raise ValueError(f"schema_name: no topic for {name!r}")
        return self._k(topic)


def sync_of(token_key: str) -> str:
    """The barrier queryable of the node whose liveliness token is ``token_key`` (``…/alive/…`` → ``…/@sync/…``)."""
    alive, sync = f"/{TABLE['alive'].chunk}/", f"/{TABLE['sync'].chunk}/"
    if alive not in token_key:
        raise ValueError(f"token_key: expected a liveliness key 'fp/<rig>/alive/<role>…', got {token_key!r}")
    return token_key.replace(alive, sync, 1)


def keys(rig: str) -> Keys:
    """Key expressions of a rig, e.g. ``keys("bench").rf == "fp/bench/rf"``."""
    return Keys(rig)


def parse_key(key: str) -> tuple[str, str]:
    """``"fp/<rig>/<topic...>"`` → ``(rig, topic)``; ValueError for other keys."""
    parts = str(key).split("/", 2)
    if len(parts) != 3 or parts[0] != PREFIX or not parts[1] or not parts[2]:
        raise ValueError(f"key: expected '{PREFIX}/<rig>/<topic>', got {key!r}")
    return parts[1], parts[2]
