"""The Demonstrations folder's form follows the picked demonstration's stored metadata (the outcome
stored at Stop, a save from another browser) unless it holds edits not saved yet, so Save never
writes back values the page showed before they changed on disk."""

from __future__ import annotations

import viser

from services.panel.library import Library
from services.panel.teaching import Teaching
from tests.conftest import free_port
from tests.unit.panel_recordings import write_demo


def teaching_on(recordings) -> tuple[viser.ViserServer, Teaching]:
    server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    return server, Teaching(server, recordings, lambda verb, request: [], lambda: None, lambda name: None)


def test_the_form_shows_an_outcome_stored_after_the_demonstration_was_picked(tmp_path):
    path = write_demo(tmp_path / "demo.mcap")
    Library(tmp_path).update(path, label="lid on")  # a sidecar, outcome unknown, as Start recording leaves it
    server, teaching = teaching_on(tmp_path)
    try:
        teaching._do_scan()
        assert (teaching.pick.value, teaching.label.value, teaching.outcome.value) == ("demo", "lid on", "unknown")
        Library(tmp_path).update(path, outcome="success")  # what Stop (success) stores
        teaching._do_scan()
        assert teaching.outcome.value == "success"
        teaching.split.value = "validation"  # the teacher's edit, then Save: the outcome survives
        teaching._do_save(path, {"label": teaching.label.value, "split": teaching.split.value,
                                 "outcome": teaching.outcome.value, "layout": teaching.picked_layout.value})
        meta = Library(tmp_path).scan()[0].meta
        assert (meta.split, meta.outcome) == ("validation", "success")
    finally:
        teaching.worker.shutdown()
        server.stop()


def test_edits_not_saved_yet_are_kept_when_the_stored_metadata_changes(tmp_path):
    path = write_demo(tmp_path / "demo.mcap")
    server, teaching = teaching_on(tmp_path)
    try:
        teaching._do_scan()
        teaching.label.value = "typed, not saved"
        Library(tmp_path).update(path, outcome="failure")  # another browser's save
        teaching._do_scan()
        assert (teaching.label.value, teaching.outcome.value) == ("typed, not saved", "unknown")
    finally:
        teaching.worker.shutdown()
        server.stop()
