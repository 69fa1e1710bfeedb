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
    stamp = "import sys, time\nt0 = time.time()\ntime.sleep(2.0)\nopen(sys.argv[1], 'w').write(f'{t0} {time.time()}')"
    lock = str(tmp_path / "machine.lock")
    procs = [subprocess.Popen([sys.executable, str(SCRIPT), "--out", str(tmp_path / f"load{i}.json"), "--lock", lock,
                               "--", sys.executable, "-c", stamp, str(tmp_path / f"span{i}")]) for i in range(2)]
    assert [p.wait(timeout=60) for p in procs] == [0, 0]
    (a0, a1), (b0, b1) = (map(float, (tmp_path / f"span{i}").read_text().split()) for i in range(2))
    assert a1 <= b0 or b1 <= a0  # no overlap
    recs = [json.loads((tmp_path / f"load{i}.json").read_text()) for i in range(2)]
    waiter = max(recs, key=lambda r: r["lock_wait_s"])
    # 2 s each: a Python's start-up on a loaded machine (up to a second or so) stays well under it
    assert waiter["lock_wait_s"] >= 1.0  # it waited for (most of) the other's 2 s
    # and its own time is its command's alone (>= 2 s): with the wait in it, it would be >= wait + 2 s
    assert 2.0 <= waiter["wall_s"] < waiter["lock_wait_s"] + 2.0
    with open(lock, "a") as held:  # a queue holds the machine: `--lock none` still runs at once
        fcntl.flock(held, fcntl.LOCK_EX)
        rc = subprocess.run([sys.executable, str(SCRIPT), "--out", str(tmp_path / "free.json"), "--lock", "none", "--",
                             sys.executable, "-c", "pass"], timeout=30).returncode
    assert rc == 0 and json.loads((tmp_path / "free.json").read_text())["lock_wait_s"] == 0


def test_a_missing_command_is_an_error(tmp_path):
    proc = subprocess.run([sys.executable, str(SCRIPT), "--out", str(tmp_path / "x.json")], capture_output=True,
                          text=True)
    assert proc.returncode != 0 and "no command" in proc.stderr
