"""What ``swanky-host`` does before converting anything, kept cheap (issue 13: whole-process
time of a bag conversion): the app's heavy import runs without the garbage collector."""

from __future__ import annotations

import gc
import json
import os
import subprocess
import sys

from host_bridge import app, cli

# A fresh interpreter: which collections ran during the import, and the collector afterwards.
FIRST_IMPORT = """
import gc, json, sys
from host_bridge import cli
collections = []
gc.callbacks.append(lambda phase, info: collections.append(info["generation"]) if phase == "start" else None)
assert "host_bridge.app" not in sys.modules and "rerun" not in sys.modules
cli.import_app_uncollected()
print(json.dumps({
    "collections": collections, "enabled": gc.isenabled(), "frozen": gc.get_freeze_count(),
    "imported": ["host_bridge.app" in sys.modules, "rerun" in sys.modules],
}))
"""


def test_the_first_import_of_the_app_runs_no_collection_and_freezes_what_it_made() -> None:
    env = {**os.environ, "_ROS_WHEELS_BOOTSTRAP_COMPLETE": "1"}
    done = subprocess.run([sys.executable, "-c", FIRST_IMPORT], capture_output=True, text=True,
                          env=env, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    found = json.loads(done.stdout)
    assert found["collections"] == []
    assert found["enabled"] is True
    assert found["imported"] == [True, True]
    # Rerun's archetypes, numpy, pyarrow: ~100k objects here; far more than a bare interpreter's.
    assert found["frozen"] > 50_000


def test_a_second_call_leaves_the_collector_as_it_was() -> None:
    assert app.__name__ in sys.modules  # imported above: this process's objects stay collectable
    frozen = gc.get_freeze_count()
    cli.import_app_uncollected()
    assert (gc.get_freeze_count(), gc.isenabled()) == (frozen, True)
    gc.disable()
    try:
        cli.import_app_uncollected()
        assert (gc.get_freeze_count(), gc.isenabled()) == (frozen, False)
    finally:
        gc.enable()
