"""core/lazy.py: a module named at a module's top and imported on its first use."""

from __future__ import annotations

import sys

import pytest

from vprflow.core.lazy import lazy_import


def test_a_lazy_module_is_imported_at_its_first_read_and_reads_what_the_module_holds_then(
    tmp_path, monkeypatch
):
    (tmp_path / "vprflow_lazy_probe.py").write_text("def answer():\n    return 1\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "vprflow_lazy_probe", raising=False)
    probe = lazy_import("vprflow_lazy_probe")
    assert "vprflow_lazy_probe" not in sys.modules
    assert probe.answer() == 1
    real = sys.modules["vprflow_lazy_probe"]
    # A name the module rebinds later (as a test's monkeypatch does) reads as rebound.
    monkeypatch.setattr(real, "answer", lambda: 2)
    assert probe.answer() == 2
    monkeypatch.delitem(sys.modules, "vprflow_lazy_probe")


def test_a_lazy_module_that_cannot_be_imported_fails_at_its_first_read():
    missing = lazy_import("vprflow_no_such_module")
    with pytest.raises(ModuleNotFoundError, match="vprflow_no_such_module"):
        getattr(missing, "anything")  # noqa: B009 (the read is what fails)
