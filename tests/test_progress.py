"""calib.progress in a log (stderr not a terminal): one line at the end, and running lines
for long work."""
import io
import time

from calib.progress import OneLine, progress


def test_short_work_writes_one_line():
    buf = io.StringIO()
    for _ in progress(range(3), desc="candidates", unit="model", file=buf):
        pass
    lines = buf.getvalue().splitlines()
    assert len(lines) == 1 and lines[0].startswith("candidates: 3/3 model in ")


def test_long_work_writes_running_lines_then_the_last():
    buf = io.StringIO()
    bar = OneLine(range(4), desc="candidates", unit="model", file=buf, heartbeat_s=0.02)
    for _ in bar:
        time.sleep(0.03)          # every item crosses the heartbeat
    lines = buf.getvalue().splitlines()
    assert [ln.split(",")[0] for ln in lines[:-1]] == [f"candidates: {k}/4 model" for k in (1, 2, 3, 4)]
    assert all(ln.endswith("s so far") for ln in lines[:-1])
    assert lines[-1].startswith("candidates: 4/4 model in ")


def test_update_counts_and_close_is_once():
    buf = io.StringIO()
    bar = OneLine(total=10, desc="fit", unit="step", file=buf, heartbeat_s=1e9)
    bar.update(4)
    bar.update(6)
    bar.close()
    bar.close()
    lines = buf.getvalue().splitlines()
    assert len(lines) == 1 and lines[0].startswith("fit: 10/10 step in ")
