"""vprflow.core.errors: how a bad value is quoted in a message; and the error for an
output folder that cannot be written (vprflow.core.files.check_writable)."""

import errno
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from vprflow.core.errors import PlanError, short_repr
from vprflow.core.files import check_writable


def test_a_short_value_is_quoted_whole():
    assert short_repr("a.jpg") == "'a.jpg'"
    assert short_repr("a.jpg", quote=False) == "a.jpg"


def test_a_long_value_is_cut_and_says_how_long_it_was():
    value = list(range(1000))
    text = short_repr(value, limit=100)
    assert len(text) <= 100
    assert text.startswith("[0, 1, 2") and text.endswith(f"... ({len(repr(value))} characters)")


@pytest.mark.parametrize(
    "code, remedy",
    [
        (errno.EROFS, "remount it read-write, or run from a copy"),
        (errno.EACCES, "give this user write permission on it (chmod, chown), or run from"),
    ],
)
def test_an_output_folder_that_cannot_be_written_is_named_with_what_to_do(
    tmp_path, monkeypatch, code, remedy
):
    """A read-only file system or another user's folder (root writes over any mode
    bits, so the refusal is made where the file is created)."""
    results = tmp_path / "results"
    results.mkdir()
    real_open = os.open

    def refuse(path, *args, **kwargs):
        if Path(path).parent == results:
            raise OSError(code, os.strerror(code), str(path))
        return real_open(path, *args, **kwargs)

    monkeypatch.setattr(os, "open", refuse)
    with pytest.raises(PlanError) as caught:
        check_writable(results)
    message = str(caught.value)
    assert message.startswith(f"{results}: cannot write there ({os.strerror(code)})"), message
    assert "a dry run too" in message and remedy in message
    with pytest.raises(PlanError) as caught:
        check_writable(results / "logs")  # missing: the folder it would be made in
    assert str(caught.value).startswith(f"{results} (where logs/ is to be made): cannot write")
    monkeypatch.undo()
    check_writable(results)
    check_writable(results / "logs")
    assert list(results.iterdir()) == []  # no probe left, no folder made


CHECK_READ_ONLY = """
mount --bind {folder} {folder} && mount -o remount,bind,ro {folder} || exit 77
{python} -c 'from vprflow.core.files import check_writable; check_writable("{folder}")'
"""


def test_a_results_folder_on_a_read_only_mount_is_named(tmp_path):
    """The same on a real read-only bind mount, where this machine lets a test make one
    (root in a fresh mount namespace)."""
    if shutil.which("unshare") is None:
        pytest.skip("no unshare here to make a read-only mount")
    results = tmp_path / "results"
    results.mkdir()
    script = CHECK_READ_ONLY.format(folder=results, python=sys.executable)
    run = subprocess.run(["unshare", "-m", "sh", "-c", script], capture_output=True, text=True)
    if run.returncode == 77 or "unshare:" in run.stderr:
        pytest.skip(f"cannot make a read-only mount here: {run.stderr.strip()}")
    assert run.returncode == 1, run.stderr
    assert f"PlanError: {results}: cannot write there (Read-only file system)" in run.stderr
    assert "remount it read-write" in run.stderr
