"""Pure helpers of the recorder service: file names, key filters, health counters."""

from __future__ import annotations

from collections import Counter

import pytest

from services.recorder.service import check_pattern, default_path, dropped, is_internal


def test_default_path_is_timestamped_and_never_reuses_a_name(tmp_path):
    first = default_path(tmp_path, now=0.0)
    assert first.parent == tmp_path and first.name.startswith("xm-") and first.suffix == ".mcap"
    first.write_bytes(b"")
    second = default_path(tmp_path, now=0.0)
    assert second != first and second.name == first.stem + "-2.mcap"


def test_at_keys_are_internal_wherever_the_chunk_is():
    assert is_internal("xm/glove/left/@health") and is_internal("xm/recorder/main/@cmd/start")
    assert is_internal("@/session/x") and not is_internal("xm/glove/left/tactile")
    assert not is_internal("xm/a@b/c")  # only a chunk starting with @ is verbatim-internal


def test_patterns_are_checked_before_any_file_is_opened():
    assert check_pattern("xm/glove/*/tactile") == "xm/glove/*/tactile"
    for bad in ("xm//x", "xm/a/", "other/**"):
        with pytest.raises(ValueError, match="keys"):
            check_pattern(bad)


def test_dropped_groups_node_error_counters_by_kind_and_key():
    errors = Counter({"unregistered_key:xm/odd": 3, "bad_payload:xm/clock": 2, "queue_overflow": 4,
                      "handler_error:xm/clock": 1})
    assert dropped(errors) == {"unregistered_key": {"xm/odd": 3}, "bad_payload": {"xm/clock": 2},
                               "queue_overflow": 4}
