"""The run folder's lock: one writer, re-entrant in a process, stale locks taken over, the folder left clean."""
from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from dibrgs_core.common.errors import InputError, RunFolderBusy
from dibrgs_core.common.lock import LOCK_NAME, acquire, holder, release, run_folder_lock

REPO = Path(__file__).resolve().parents[2]
HOLD = ("import sys, time; from dibrgs_core.common.lock import acquire; acquire(sys.argv[1], sys.argv[2]); "
        "print('locked', flush=True); time.sleep(600)")


def _hold(folder: Path, command: str = "train") -> subprocess.Popen:
    p = subprocess.Popen([sys.executable, "-c", HOLD, str(folder), command], stdout=subprocess.PIPE, text=True,
                         cwd=REPO)
    assert p.stdout.readline().strip() == "locked"
    return p


def test_second_process_is_refused_with_the_holder(tmp_path):
    work = tmp_path / "w"
    p = _hold(work, "train")
    try:
        info = holder(work)
        assert info["pid"] == p.pid and info["host"] == socket.gethostname() and info["command"] == "train"
        with pytest.raises(RunFolderBusy, match=rf"in use by pid {p.pid} on {socket.gethostname()} \(train, since "):
            acquire(work, "eval")
    finally:
        p.kill()
        p.wait()
    # The holder died (SIGKILL): its lock file stays, and is stale.
    assert json.loads((work / LOCK_NAME).read_text())["pid"] == p.pid
    with run_folder_lock(work, "eval"):
        assert holder(work)["pid"] == os.getpid() and holder(work)["command"] == "eval"
    assert not (work / LOCK_NAME).exists() and work.is_dir()


def test_reentrant_in_one_process_and_released_last(tmp_path):
    work = tmp_path / "w"
    with run_folder_lock(work, "train"):
        with run_folder_lock(work / "." , "train"):  # the same folder by another spelling
            assert (work / LOCK_NAME).exists()
        assert (work / LOCK_NAME).exists()
        r = subprocess.run([sys.executable, "-c", "import sys; from dibrgs_core.common.lock import acquire; "
                            "acquire(sys.argv[1], 'x')", str(work)], capture_output=True, text=True, cwd=REPO)
        assert r.returncode != 0 and "RunFolderBusy" in r.stderr
    assert not (work / LOCK_NAME).exists()
    release(work)  # releasing what is not held is harmless


def test_a_folder_made_for_nothing_is_removed(tmp_path):
    with run_folder_lock(tmp_path / "new", "render"):
        pass
    assert not (tmp_path / "new").exists()
    with run_folder_lock(tmp_path / "kept", "render"):
        (tmp_path / "kept" / "out.png").write_bytes(b"x")
    assert (tmp_path / "kept" / "out.png").exists() and not (tmp_path / "kept" / LOCK_NAME).exists()


def test_a_file_is_not_a_run_folder(tmp_path):
    f = tmp_path / "f"
    f.write_text("x")
    with pytest.raises(InputError, match="is a file, not a folder"):
        acquire(f, "train")
    assert f.read_text() == "x"


def test_many_processes_one_winner(tmp_path):
    """Eight processes race for one folder: exactly one holds it (the winner holds on until all have tried)."""
    work = tmp_path / "w"
    code = ("import sys; from dibrgs_core.common.lock import acquire\n"
            "try:\n    acquire(sys.argv[1], 'x'); print('won', flush=True); sys.stdin.read()\n"
            "except Exception as e:\n    print('lost', type(e).__name__, flush=True)\n")
    procs = [subprocess.Popen([sys.executable, "-c", code, str(work)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                              text=True, cwd=REPO) for _ in range(8)]
    outs = [p.stdout.readline().split() for p in procs]  # every process has tried before the winner lets go
    for p in procs:
        p.stdin.close()
        p.wait(timeout=60)
    assert sum(o[0] == "won" for o in outs) == 1, outs
    assert all(o == ["lost", "RunFolderBusy"] for o in outs if o[0] != "won"), outs
