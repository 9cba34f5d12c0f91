"""The atomic writer (links followed, non-regular targets refused, umask modes, no temporary files left),
strict JSON, content digests and the one-line messages for operating-system errors."""
from __future__ import annotations

import errno
import json
import os
import stat
from pathlib import Path

import numpy as np
import pytest

from dibrgs_core.common.digest import Digest, file_digest
from dibrgs_core.common.errors import InputError, RunFolderBusy, exit_code, explain
from dibrgs_core.common.fileio import atomic_path, dumps, write_json, write_text


def test_symlink_is_followed_and_kept(tmp_path):
    target = tmp_path / "a" / "real.txt"
    target.parent.mkdir()
    target.write_text("old")
    link = tmp_path / "link.txt"
    link.symlink_to(target)
    chain = tmp_path / "chain.txt"
    chain.symlink_to(link)
    write_text(chain, "new")
    assert chain.is_symlink() and link.is_symlink() and target.read_text() == "new"
    dangling = tmp_path / "dangling.txt"
    dangling.symlink_to(tmp_path / "a" / "later.txt")
    write_text(dangling, "made")
    assert dangling.is_symlink() and (tmp_path / "a" / "later.txt").read_text() == "made"
    assert not list(tmp_path.rglob(".*.tmp*"))


@pytest.mark.parametrize("kind", ["folder", "fifo", "socket", "link-to-folder"])
def test_non_regular_targets_are_refused_and_left_alone(tmp_path, kind):
    p = tmp_path / "target"
    if kind == "folder":
        p.mkdir()
    elif kind == "fifo":
        os.mkfifo(p)
    elif kind == "socket":
        import socket

        s = socket.socket(socket.AF_UNIX)
        s.bind(str(p))
    else:
        (tmp_path / "d").mkdir()
        p.symlink_to(tmp_path / "d")
    mode = os.lstat(p).st_mode
    with pytest.raises(InputError, match="not a regular file") as e:
        write_text(p, "x")
    assert str(p) in str(e.value)
    assert os.lstat(p).st_mode == mode and not list(tmp_path.rglob(".*.tmp*"))


def test_modes_follow_the_umask_and_replaced_files_keep_theirs(tmp_path):
    for um, want in ((0o022, 0o644), (0o077, 0o600), (0o002, 0o664)):
        old = os.umask(um)
        try:
            write_text(tmp_path / f"f{um:o}.txt", "x")
        finally:
            os.umask(old)
        assert stat.S_IMODE((tmp_path / f"f{um:o}.txt").stat().st_mode) == want
    p = tmp_path / "kept.txt"
    p.write_text("x")
    os.chmod(p, 0o604)
    write_text(p, "y")
    assert stat.S_IMODE(p.stat().st_mode) == 0o604 and p.read_text() == "y"


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    p = tmp_path / "f.txt"
    p.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(p) as tmp:
            tmp.write_text("half")
            raise RuntimeError("killed half-way")
    assert p.read_text() == "old" and not list(tmp_path.glob(".*"))
    with pytest.raises(OSError) as e:  # an error from a writer to a file object names the target
        with atomic_path(p) as tmp:
            raise OSError(errno.ENOSPC, "No space left on device")
    assert e.value.filename == str(p) and "no space left" in explain(e.value)


def test_strict_json(tmp_path):
    obj = {"a": float("inf"), "b": [float("nan"), np.float32(-np.inf), np.float64(1.5)], "c": np.arange(3),
           "d": Path("/x"), "e": np.int64(3), "f": (1, 2), 4: True}
    write_json(tmp_path / "m.json", obj)
    text = (tmp_path / "m.json").read_text()
    assert "Infinity" not in text and "NaN" not in text
    back = json.loads(text, parse_constant=lambda c: pytest.fail(c))
    assert back == {"a": None, "b": [None, None, 1.5], "c": [0, 1, 2], "d": "/x", "e": 3, "f": [1, 2], "4": True}
    assert dumps({"x": float("nan")}, indent=None) == '{"x": null}'
    with pytest.raises(TypeError):
        dumps({"x": object()})


def test_explain_names_the_path_and_what_to_do():
    cases = {errno.EACCES: "permission denied; choose a folder you can write",
             errno.ENOSPC: "no space left on the device; free some space",
             errno.EROFS: "read-only file system; choose a folder on a writable",
             errno.ENOTDIR: "a part of this path is a file, not a folder",
             errno.EISDIR: "is a folder, not a file; give a file name",
             errno.EDQUOT: "disk quota exceeded"}
    for no, says in cases.items():
        line = explain(OSError(no, os.strerror(no), "/some/path"))
        assert line.startswith("/some/path: ") and says in line, line
        assert exit_code(OSError(no, "x")) == 1
    assert explain(OSError(errno.EXDEV, "Invalid cross-device link", "/a", None, "/b")).startswith("/a -> /b: ")
    assert explain(InputError("/f", "bad")) == "/f: bad" and exit_code(InputError(None, "x")) == 2
    assert exit_code(RunFolderBusy("/w", "in use")) == 75
    assert explain(KeyError("x")) is None and exit_code(KeyError("x")) == 1


def test_digests():
    a = np.arange(6, dtype=np.float32)
    assert Digest("k").array(a).hex() == Digest("k").array(a.copy()).hex()
    assert Digest("k").array(a).hex() != Digest("k").array(a.astype(np.float64)).hex()  # dtype counts
    assert Digest("k").array(a).hex() != Digest("k").array(a.reshape(2, 3)).hex()  # shape counts
    assert Digest("k").array(a).hex() != Digest("j").array(a).hex()  # the kind counts
    assert Digest("k").json({"b": 1, "a": 2}).hex() == Digest("k").json({"a": 2, "b": 1}).hex()
    assert Digest("k").text("ab").text("c").hex() != Digest("k").text("a").text("bc").hex()
    assert len(Digest("k").hex()) == 24


def test_file_digest(tmp_path):
    p = tmp_path / "f"
    p.write_bytes(b"x" * 3_000_000)
    d = file_digest(p)
    p.write_bytes(b"x" * 2_999_999 + b"y")
    assert file_digest(p) != d and len(d) == 24
