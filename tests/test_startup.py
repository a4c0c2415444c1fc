"""The start-up's garbage-collector settings (``mideepbasis.startup``): imports without collections,
the collector as it was afterwards, a program's own frozen objects never thawed."""

from __future__ import annotations

import gc
import json
import subprocess
import sys

import pytest

from mideepbasis import startup


@pytest.fixture
def collector():
    """The collector's state restored after each test (these tests change it on purpose)."""
    enabled, frozen_setting = gc.isenabled(), startup.freeze_imports
    yield
    startup.freeze_imports = frozen_setting
    gc.unfreeze()
    gc.enable() if enabled else gc.disable()


class Node:
    def __init__(self):
        self.me = self  # a reference cycle: only the collector frees it


def test_nothing_is_collected_inside_and_the_collector_is_on_again_after(collector):
    gc.enable()
    collections = []
    callback = lambda phase, info: collections.append(info["generation"]) if phase == "stop" else None  # noqa: E731
    gc.callbacks.append(callback)
    try:
        with startup.collection_paused():
            assert not gc.isenabled()
            made = [Node() for _ in range(20_000)]  # far past the youngest generation's threshold (700)
            during = len(collections)
        assert during == 0
        assert gc.isenabled()
        # What was made went to the oldest generation: the young generations start empty.
        assert gc.get_count()[0] < 700 and gc.get_count()[1] == 0
        assert gc.get_freeze_count() == 0
    finally:
        gc.callbacks.remove(callback)
    del made


def test_a_paused_collector_stays_paused(collector):
    gc.disable()
    with startup.collection_paused():
        pass
    assert not gc.isenabled()


def test_what_a_program_froze_itself_stays_frozen(collector):
    gc.freeze()
    frozen = gc.get_freeze_count()
    assert frozen > 0
    with startup.collection_paused():
        made = [Node() for _ in range(1_000)]
    assert gc.get_freeze_count() == frozen  # not thawed, and the new objects not frozen with it
    del made


def test_with_freeze_imports_what_was_made_is_out_of_every_collection(collector):
    startup.freeze_imports = True
    with startup.collection_paused():
        made = [Node() for _ in range(1_000)]
    assert gc.get_freeze_count() >= 1_000
    gc.unfreeze()
    del made


def test_cycles_made_after_the_start_up_are_still_collected(collector):
    startup.freeze_startup_objects()
    assert startup.freeze_imports
    with startup.collection_paused():
        pass
    Node()  # garbage at once: only a collection frees it
    assert gc.collect() >= 1


def test_importing_the_package_leaves_a_programs_collector_as_it_was():
    """A library user's process: the collector on, nothing frozen, after the package and its
    rendering (drjit, Mitsuba) are imported."""
    script = ("import gc, json, mideepbasis, mideepbasis.render; "
              "print(json.dumps([gc.isenabled(), gc.get_freeze_count()]))")
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    assert json.loads(result.stdout.strip().splitlines()[-1]) == [True, 0]
