"""scripts/idle_run.py: a command's CPU time against the whole machine's, and its exit status."""
import fcntl
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "idle_run.py"


def test_records_the_commands_cpu_and_the_machines_and_passes_the_exit_status(tmp_path):
    out = tmp_path / "load.json"
    busy = "import time\nt = time.process_time()\nwhile time.process_time() - t < 0.3: pass\nraise SystemExit(3)"
    rc = subprocess.run([sys.executable, str(SCRIPT), "--out", str(out), "--lock", str(tmp_path / "lock"), "--",
                         sys.executable, "-c", busy]).returncode
    assert rc == 3
    rec = json.loads(out.read_text())
    assert rec["returncode"] == 3 and rec["child_cpu_s"] >= 0.3  # the command's own CPU time
    assert rec["machine_busy_cpu_s"] >= rec["child_cpu_s"] - 0.05  # the machine's includes it (tick rounding)
    assert rec["foreign_cpu_s"] >= 0 and rec["foreign_share"] == rec["foreign_cpu_s"] / (rec["wall_s"] * rec["cpus"])
    assert rec["idle"] == (rec["foreign_share"] <= rec["max_foreign"])
    assert 0 <= rec["lock_wait_s"] < 5


def test_timed_commands_on_one_machine_take_turns(tmp_path):
    """Two timed commands sharing the machine's lock run one after the other (the second waits,
    and its wait is outside its measurement); `--lock none` does not wait."""
    stamp = "import sys, time\nt0 = time.time()\ntime.sleep(0.6)\nopen(sys.argv[1], 'w').write(f'{t0} {time.time()}')"
    lock = str(tmp_path / "machine.lock")
    procs = [subprocess.Popen([sys.executable, str(SCRIPT), "--out", str(tmp_path / f"load{i}.json"), "--lock", lock,
                               "--", sys.executable, "-c", stamp, str(tmp_path / f"span{i}")]) for i in range(2)]
    assert [p.wait(timeout=60) for p in procs] == [0, 0]
    (a0, a1), (b0, b1) = (map(float, (tmp_path / f"span{i}").read_text().split()) for i in range(2))
    assert a1 <= b0 or b1 <= a0  # no overlap
    recs = [json.loads((tmp_path / f"load{i}.json").read_text()) for i in range(2)]
    waiter = max(recs, key=lambda r: r["lock_wait_s"])
    assert waiter["lock_wait_s"] >= 0.4  # it waited for the other's 0.6 s
    # and its own time is its command's alone (>= 0.6 s): with the wait in it, it would be >= wait + 0.6 s
    assert 0.6 <= waiter["wall_s"] < waiter["lock_wait_s"] + 0.6
    with open(lock, "a") as held:  # a queue holds the machine: `--lock none` still runs at once
        fcntl.flock(held, fcntl.LOCK_EX)
        rc = subprocess.run([sys.executable, str(SCRIPT), "--out", str(tmp_path / "free.json"), "--lock", "none", "--",
                             sys.executable, "-c", "pass"], timeout=30).returncode
    assert rc == 0 and json.loads((tmp_path / "free.json").read_text())["lock_wait_s"] == 0


def test_a_missing_command_is_an_error(tmp_path):
    proc = subprocess.run([sys.executable, str(SCRIPT), "--out", str(tmp_path / "x.json")], capture_output=True,
                          text=True)
    assert proc.returncode != 0 and "no command" in proc.stderr


def test_a_second_headline_queue_on_one_work_dir_refuses_to_start(tmp_path):
    """scripts/headline_table.sh: two queues on one WORK_DIR would train the same runs at once."""
    root = tmp_path / "dnerf"
    for s in ("bouncingballs", "hellwarrior", "jumpingjacks", "standup"):
        (root / s).mkdir(parents=True)
        (root / s / "transforms_train.json").write_text("{}")
    work = tmp_path / "work"
    work.mkdir()
    # a seed the committed records do not have, so the dry run lists its runs (HEADLINE_DRY prints them)
    env = {"HEADLINE_DRY": "1", "HEADLINE_SEEDS": "99", "PATH": "/usr/bin:/bin"}
    cmd = ["bash", str(ROOT / "scripts" / "headline_table.sh"), str(root), str(work)]
    with open(work / ".queue.lock", "w") as held:  # a queue running on WORK_DIR holds this lock
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        second = subprocess.run(cmd, capture_output=True, text=True, env=env)
        assert second.returncode == 3 and "another queue is running" in second.stderr
    alone = subprocess.run(cmd, capture_output=True, text=True, env=env)  # the lock is free again
    assert alone.returncode == 0 and "stdr-train experiment=dnerf_deform budget=cpu seed=99" in alone.stdout, alone.stderr


def test_a_studys_pause_file_stops_the_headline_queue_before_its_next_run(tmp_path):
    """WORK_DIR/pause.<name> (studies/compact.py --hold) pauses scripts/headline_table.sh between
    runs, as WORK_DIR/pause does: no run starts while it is there."""
    import os
    import signal
    import time
    root = tmp_path / "dnerf"
    for s in ("bouncingballs", "hellwarrior", "jumpingjacks", "standup"):
        (root / s).mkdir(parents=True)
        (root / s / "transforms_train.json").write_text("{}")
    code = tmp_path / "code"
    (code / "scripts").mkdir(parents=True)
    marker = tmp_path / "trained"
    (code / "scripts" / "run.sh").write_text(f"#!/bin/sh\ntouch {marker}\n")
    (code / "scripts" / "run.sh").chmod(0o755)
    work = tmp_path / "work"
    work.mkdir()
    (work / "pause.compact").write_text("")
    env = {"HEADLINE_SEEDS": "99", "HEADLINE_CODE": str(code), "PATH": "/usr/bin:/bin",
           "STDR_IDLE_LOCK": str(tmp_path / "machine.lock")}
    proc = subprocess.Popen(["bash", str(ROOT / "scripts" / "headline_table.sh"), str(root), str(work)],
                            stdout=subprocess.PIPE, text=True, env=env, start_new_session=True)
    try:
        line = proc.stdout.readline()  # the first thing it says
        assert "paused (" in line and "pause.compact" in line, line
        time.sleep(1.5)
        assert not marker.exists() and proc.poll() is None  # still waiting, nothing trained
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
