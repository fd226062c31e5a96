"""Every bad input through the real ``tt`` command line: a non-zero exit, one ``error:`` line
naming the offending file, flag or field, no traceback, nothing lost (issues 22 and 50).

The table is `tests/bad_input_cases.py` (also run by the sweep ``benchmarks/bad_inputs.py``),
with its scenarios (issue 50's second round: a full disk, ``-`` as stdout, a named pipe,
``tt designs`` over a user's files, ``tt train``'s run folder and resumed data, flags that do
not apply, messages); the tests after it cover what neither holds: resuming from a damaged
checkpoint, refusing a resume with other arguments, fsync before rename, strict JSON, the
dataset lock, a full disk in ``tt generate``, ``tt view --serve`` under SIGTERM and unique
detokenized names. Killed runs are `tests/test_kills.py`'s.
"""

from __future__ import annotations

import errno
import json
import multiprocessing as mp
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from bad_input_cases import CASES, CLASSES, SCENARIOS, make_files, noisy_detokenized, outcome  # noqa: E402

from tt.generate import GenerateConfig, generate  # noqa: E402

#: 2 shards of 2 designs x 1 episode on motions cut to 24 steps: the smallest real dataset.
DATASET = GenerateConfig(
    space="viperx", designs=4, episodes_per_design=1, designs_per_shard=2, min_steps=10, max_motion_steps=24
)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    dataset = tmp_path_factory.mktemp("dataset") / "ds"
    generate(DATASET, dataset, device="cpu", progress=False)
    return make_files(tmp_path_factory.mktemp("bad"), dataset)


class _AnyFile:
    def __getattr__(self, name: str) -> str:
        return name


def test_the_table_covers_every_class_and_command():
    from tt.cli import app, dataset_app

    assert {c.cls for c in CASES} | {s.cls for s in SCENARIOS} >= set(CLASSES) - {2, 7}  # 2 and 7 are tests below
    used = {" ".join(c.args(_AnyFile())[: 2 if c.args(_AnyFile())[0] == "dataset" else 1]) for c in CASES}
    commands = {c.name or c.callback.__name__ for c in app.registered_commands}
    commands |= {f"dataset {c.name}" for c in dataset_app.registered_commands}
    assert commands <= used, sorted(commands - used)
    assert len(CASES) >= 50


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_bad_input(case, files, tt_cli):
    result = outcome(case, files, tt_cli)
    assert result.kind in ("clear", "ok"), f"{result.kind}: {result.why}\n{result.output}"


@pytest.mark.parametrize(
    "scenario", [s for s in SCENARIOS if s.cls != 13], ids=[s.name for s in SCENARIOS if s.cls != 13]
)
def test_bad_input_scenario(scenario, files, tmp_path, single_thread):
    kind, why = scenario.run(files, tmp_path)  # class 13 (a killed tt generate) is tests/test_kills.py's
    assert kind in ("clear", "ok"), f"{kind}: {why}"


def test_atomic_write_keeps_the_old_file_and_names_it_on_a_full_disk(tmp_path, monkeypatch):
    """The safe writer itself: a failing fsync (a full disk's delayed error) leaves the old
    file, removes the temporary one and names the file; a link is written through with the
    target's permissions; a socket is refused naming the flag."""
    import socket

    import tt.kernels.files as files_mod
    from tt.kernels.errors import TTError
    from tt.kernels.files import write_text

    target = tmp_path / "target.txt"
    target.write_text("old")
    target.chmod(0o600)
    (tmp_path / "link.txt").symlink_to("target.txt")

    def full(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    with monkeypatch.context() as m:
        m.setattr(files_mod.os, "fsync", full)
        with pytest.raises(OSError) as e:
            write_text(tmp_path / "link.txt", "new")
    assert e.value.errno == errno.ENOSPC and e.value.filename == str(tmp_path / "link.txt")
    assert target.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["link.txt", "target.txt"]
    write_text(tmp_path / "link.txt", "new")
    assert (tmp_path / "link.txt").is_symlink() and target.read_text() == "new"
    assert target.stat().st_mode & 0o777 == 0o600
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.bind(str(tmp_path / "sock"))
    sock.close()
    with pytest.raises(TTError, match="--json .*sock is a socket"):
        write_text(tmp_path / "sock", "x", flag="--json")


def test_optimize_help_lists_every_method(tt_cli):
    from tt.optimizers import METHODS

    code, out = tt_cli(["optimize", "--help"])
    assert code == 0 and all(m in out for m in METHODS), out


def test_traceback_only_with_verbose(files, tt_cli):
    code, out = tt_cli(["tokenize", files.robots_dir])
    assert code == 2 and "Traceback" not in out and "error: " in out
    code, out = tt_cli(["-v", "tokenize", files.robots_dir])
    assert code == 2 and "Traceback" in out and "is a folder" in out


# ------------------------------------------------------------------ 2: resume
def _train(tt_cli, data, out, *extra) -> str:
    code, text = tt_cli(
        [
            "train",
            "--data",
            str(data),
            "--size",
            "tiny",
            "--batch-size",
            "4",
            "--device",
            "cpu",
            "--out",
            str(out),
            *extra,
        ]
    )
    assert code == 0, text
    return text


def test_resume_falls_back_to_the_newest_intact_checkpoint(files, tt_cli, tmp_path, single_thread):
    import torch

    from tt.dit.checkpoint import list_checkpoints, load_checkpoint

    run = tmp_path / "run"
    _train(tt_cli, files.episodes, run, "--steps", "4", "--config", "checkpoint_every=2")
    latest = list_checkpoints(run)[-1]
    assert latest.name == "step_0000004.pt"
    latest.write_bytes(latest.read_bytes()[:1000])  # a disk that filled up mid-write, say
    text = _train(tt_cli, files.episodes, run, "--steps", "6", "--config", "checkpoint_every=2")
    assert "step_0000004.pt" in text and "resuming from the checkpoint before it" in text, text
    assert (run / "checkpoints" / "step_0000004.pt.damaged").exists()
    straight = tmp_path / "straight"
    _train(tt_cli, files.episodes, straight, "--steps", "6", "--config", "checkpoint_every=2")
    a = load_checkpoint(list_checkpoints(run)[-1])
    b = load_checkpoint(list_checkpoints(straight)[-1])
    assert a["step"] == b["step"] == 6
    torch.testing.assert_close(a["losses"], b["losses"], rtol=0, atol=0)
    for k in b["state_dict"]:
        assert torch.equal(a["state_dict"][k], b["state_dict"][k]), k


def test_resume_with_other_data_or_learning_rate_is_refused(files, tt_cli, tmp_path, single_thread):
    run = tmp_path / "run"
    _train(tt_cli, files.episodes, run, "--steps", "1", "--config", "lr=0.001")
    code, text = tt_cli(
        [
            "train",
            "--data",
            files.episodes,
            "--size",
            "tiny",
            "--batch-size",
            "4",
            "--device",
            "cpu",
            "--steps",
            "2",
            "--config",
            "lr=0.002",
            "--out",
            str(run),
        ]
    )
    assert code == 2 and "lr" in text and "0.001" in text and "0.002" in text, text
    other = Path(files.root) / "episodes_other.npz"
    other.write_bytes(Path(files.episodes).read_bytes())
    code, text = tt_cli(
        [
            "train",
            "--data",
            str(other),
            "--size",
            "tiny",
            "--batch-size",
            "4",
            "--device",
            "cpu",
            "--steps",
            "2",
            "--config",
            "lr=0.001",
            "--out",
            str(run),
        ]
    )
    assert code == 2 and "--data" in text and "episodes_other.npz" in text, text


def test_checkpoints_are_fsynced_before_the_rename(tmp_path, monkeypatch):
    import torch

    import tt.kernels.files as files_mod
    from tt.dit.checkpoint import save_checkpoint

    events = []
    real_fsync, real_replace = os.fsync, os.replace
    monkeypatch.setattr(
        files_mod.os, "fsync", lambda fd: (events.append(("fsync", os.readlink(f"/proc/self/fd/{fd}"))), real_fsync(fd))
    )
    monkeypatch.setattr(files_mod.os, "replace", lambda a, b: (events.append(("replace", str(b))), real_replace(a, b)))
    path = save_checkpoint(tmp_path / "checkpoints" / "step_0000001.pt", {"step": 1, "x": torch.zeros(3)})
    kinds = [k for k, _ in events]
    assert kinds == ["fsync", "replace", "fsync"], events  # the file, the rename, its folder
    assert events[0][1].startswith(str(path.parent)) and events[1][1] == str(path) and events[2][1] == str(path.parent)


# ------------------------------------------------------------------ 4: strict JSON
def test_json_writes_null_for_nan_and_says_why(files, tt_cli, tmp_path):
    out = tmp_path / "v.json"
    code, text = tt_cli(
        ["validate", "--design", files.designs + "#0", "--motion", files.motion_far, "--json", str(out)]
    )
    assert code == 0, text
    data = json.loads(out.read_text(), parse_constant=lambda c: pytest.fail(f"bare {c} in {out}"))
    assert data["metrics"][0]["pos_err"] is None  # the robot ended at its first step: no error to average
    assert "metrics[0].pos_err" in data["null_values"]["fields"] and "JSON has no NaN" in data["null_values"]["why"]
    assert "written as null" in text


# ------------------------------------------------------------------ 5: lock, disk, server
def _take_lock(path, barrier, attempts, results):
    from tt.tokens.lock import DatasetLock
    from tt.tokens.store import DatasetError

    barrier.wait()
    try:
        with DatasetLock(path):
            with attempts.get_lock():
                attempts.value += 1
            deadline = time.monotonic() + 20
            while attempts.value < 4 and time.monotonic() < deadline:  # hold it until every run has tried
                time.sleep(0.01)
            results.put("won")
    except DatasetError:
        with attempts.get_lock():
            attempts.value += 1
        results.put("refused")


def test_stale_lock_takeover_has_one_winner(tmp_path):
    (tmp_path / ".lock").write_text(json.dumps({"host": os.uname().nodename, "pid": 2**22 + 12345}))  # a dead run
    ctx = mp.get_context("fork")
    barrier, attempts, results = ctx.Barrier(4), ctx.Value("i", 0), ctx.Queue()
    procs = [ctx.Process(target=_take_lock, args=(tmp_path, barrier, attempts, results)) for _ in range(4)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(60)
    outcomes = sorted(results.get(timeout=5) for _ in procs)
    assert outcomes == ["refused", "refused", "refused", "won"], outcomes
    assert not (tmp_path / ".lock").exists()


def test_full_disk_during_generation_says_how_to_resume(tt_cli, tmp_path, monkeypatch):
    import tt.generate as gen

    def full(config, index, out, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(Path(out) / ".partial" / f"s{index:06d}"))

    monkeypatch.setattr(gen, "generate_shard", full)
    code, text = tt_cli(
        [
            "generate",
            "--designs",
            "2",
            "--config",
            "designs_per_shard=1",
            "--out",
            str(tmp_path / "ds"),
            "--device",
            "cpu",
        ]
    )
    assert code == 2 and "Traceback" not in text, text
    assert "No space left on device" in text and "0 of 2 shards" in text and "re-run the same command to resume" in text


def test_view_serve_stops_its_meshcat_server_on_sigterm(tmp_path):
    from tt.sim.designs import get_space, save_designs

    save_designs(get_space("viperx").sample(1, 0), tmp_path / "designs.json")
    proc = subprocess.Popen(
        [sys.executable, "-m", "tt.cli", "view", str(tmp_path / "designs.json"), "--serve"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        cwd=tmp_path,
    )
    try:
        lines = []
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            lines.append(line)
            if "serving" in line or not line:
                break
        assert any("meshcat viewer" in x for x in lines), "".join(lines)
        children = Path(f"/proc/{proc.pid}/task/{proc.pid}/children").read_text().split()
        assert children, "no meshcat server process"
        proc.send_signal(signal.SIGTERM)
        rest = proc.communicate(timeout=30)[0]
    finally:
        proc.kill()
    assert "stopped the meshcat server" in rest, (proc.returncode, "".join(lines), rest)
    for pid in children:
        stat = Path(f"/proc/{pid}/stat")
        assert not stat.exists() or stat.read_text().split(")")[-1].split()[0] == "Z", (
            f"meshcat server {pid} still runs"
        )


# ------------------------------------------------------------------ 7: detokenizer names
def test_detokenized_names_are_unique_at_any_noise():
    repeated = []
    for r in noisy_detokenized():
        if not r.ok and "repeated name" in r.error:
            repeated.append(r.error)
        if r.ok:
            import mujoco

            names = [mujoco.mj_id2name(r.model, mujoco.mjtObj.mjOBJ_JOINT, j) for j in range(r.model.njnt)]
            assert len(set(names)) == len(names)
    assert not repeated, repeated[:3]
