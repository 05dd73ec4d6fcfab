"""flightsim.core.lazy: kernels modules loaded at their first use, and kernel builders that hold the parsing lock
(CPython 3.11's AST constructor must not run in two threads at once)."""
import sys
import threading

from flightsim.core.lazy import PARSING, lazy_module, parsed


def test_a_lazy_module_imports_at_its_first_look_up(tmp_path, monkeypatch):
    (tmp_path / "lazy_probe_module.py").write_text("VALUE = 7\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "lazy_probe_module", raising=False)
    probe = lazy_module("lazy_probe_module")
    assert "lazy_probe_module" not in sys.modules and "first use" in repr(probe)
    assert probe.VALUE == 7 and sys.modules["lazy_probe_module"].VALUE == 7 and "loaded" in repr(probe)


def _held_elsewhere() -> bool:
    """Whether another thread cannot take PARSING now."""
    took = []

    def other():
        took.append(PARSING.acquire(timeout=0.05))
        if took[0]:
            PARSING.release()

    thread = threading.Thread(target=other)
    thread.start()
    thread.join()
    return not took[0]


def test_a_kernel_builder_is_cached_and_builds_holding_the_parsing_lock():
    calls = []

    @parsed
    def build(n):
        calls.append(n)
        return object(), _held_elsewhere()

    made, held = build(3)
    assert held and build(3)[0] is made and calls == [3]
    assert not _held_elsewhere()  # released after
