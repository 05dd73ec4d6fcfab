"""Modules loaded on first use. The command line imports every registered part to know its settings, but a run
needs the kernels of the parts it flies only: a kernels module defines its Warp kernels when it is imported (the
photon, waveform, FSM, galvo, panoramic, fixed and N-prism kernels together ~0.1 s of a 2-core machine's start,
none of which a Risley run to LAS uses). A part's module names its kernels module with :func:`lazy_module` and
uses it as usual (``photon.PhotonDetector()``); the module loads at the first such look-up."""
from __future__ import annotations

import importlib
import threading
from types import ModuleType

PARSING = threading.RLock()
"""Held while a lazy module imports and while a tile writer's thread first loads laspy. CPython 3.11 keeps the AST
constructor's recursion depth per interpreter, not per thread: two threads building syntax trees at once (Warp's
decorators parse each kernel's source as a kernels module imports; laspy's import runs NumPy's literal_eval of
dtype strings) can fail with SystemError ("AST constructor recursion depth mismatch")."""


class LazyModule:
    """Stands in for module ``name`` until an attribute is looked up on it, which imports the module (under
    :data:`PARSING` and Python's import lock: threads that look up at once get the one module) and returns the
    module's attribute."""

    def __init__(self, name: str):
        self._name = name
        self._module: ModuleType | None = None

    def __getattr__(self, attribute: str):
        module = self._module
        if module is None:
            with PARSING:
                module = self._module = importlib.import_module(self._name)
        return getattr(module, attribute)

    def __repr__(self) -> str:
        return f"<module {self._name!r}, {'loaded' if self._module is not None else 'loaded on first use'}>"


def lazy_module(name: str) -> LazyModule:
    """The module ``name`` (dotted), imported at its first attribute look-up."""
    return LazyModule(name)
