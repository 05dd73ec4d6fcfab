"""Runs the copc.js reader scripts of tests/js (an independent LAS/COPC reader that shares no code with
laspy) on a file and returns what they print as JSON. Node.js and `npm ci --prefix tests/js` are part of the
README's test set-up, so their absence fails the test rather than skipping it."""
from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

JS_DIR = Path(__file__).parent / "js"


def read_with_copcjs(script: str, path: Path) -> dict:
    """JSON output of ``tests/js/<script>`` run by node on ``path``."""
    node = shutil.which("node")
    if node is None:
        pytest.fail("node (v18+) is needed for the copc.js reader checks; install Node.js")
    if not (JS_DIR / "node_modules" / "copc").is_dir():
        pytest.fail(f"copc.js is not installed: run `npm ci --prefix {JS_DIR}`")
    result = subprocess.run([node, str(JS_DIR / script), str(path)], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)
