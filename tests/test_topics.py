"""Key expressions come from one table (services.topics): data topics, acks, dictionary operations, tokens."""

from __future__ import annotations

import pytest

from services.messages import MESSAGE_TYPES
from services.topics import ALL_RIGS, TABLE, TOPICS, keys, parse_key, sync_of


def test_every_message_type_has_one_topic() -> None:
    assert sorted(TOPICS.values()) == sorted(MESSAGE_TYPES)
    k = keys("r")
    for topic, schema in TOPICS.items():
        assert k.for_message(MESSAGE_TYPES[schema]) == k.topic(topic) == f"fp/r/{TABLE[topic].chunk}"
    assert ALL_RIGS == "fp/**" and k.all == "fp/r/**" and k.ingest == "fp/r/ingest"
    with pytest.raises(ValueError, match="topic"):
        k.topic("nope")
    with pytest.raises(AttributeError):
        k.nope  # noqa: B018


def test_acks_dictionary_and_tokens() -> None:
    k = keys("r")
    assert k.acks == ("fp/r/detections", "fp/r/errors")
    assert [k.dictionary_op(op, "a/b") for op in ("list", "get", "add", "remove", "set")] == [
        "fp/r/dictionary/list",
        "fp/r/dictionary/a/b",
        "fp/r/dictionary/add/a/b",
        "fp/r/dictionary/remove/a/b",
        "fp/r/dictionary/set",
    ]
    for op in ("add", "remove", "get"):
        with pytest.raises(ValueError):
            k.dictionary_op(op)
    with pytest.raises(ValueError, match="op"):
        k.dictionary_op("drop", "x")
    assert k.dictionary_path("fp/r/dictionary/add/a/b") == ["add", "a", "b"]
    assert k.dictionary_path("fp/r/dictionary") == [] and k.dictionary_path("fp/other/dictionary/x") == []
    assert k.alive("processor") == k.alive("processor", "processor") == "fp/r/alive/processor"
    assert k.alive("processor", "p2") == "fp/r/alive/processor/p2"
    assert k.alive_any("processor") == "fp/r/alive/processor/**"
    assert keys("*").alive("recorder") == "fp/*/alive/recorder"
    assert k.sync("processor", "p2") == sync_of(k.alive("processor", "p2")) == "fp/r/@sync/processor/p2"
    assert k.sync_any("processor") == "fp/r/@sync/processor/**" and keys("*").sync("recorder") == "fp/*/@sync/recorder"
    with pytest.raises(ValueError, match="token_key"):
        sync_of("fp/r/rf")
    with pytest.raises(ValueError, match="role"):
        k.alive("a/b")
    assert parse_key(k.alive("viewer")) == ("r", "alive/viewer")
