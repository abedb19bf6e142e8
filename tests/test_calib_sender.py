"""The serial link against a fake printer on a pseudo-terminal: pyserial opens the pty's
slave end exactly as it opens /dev/ttyUSB0, and a thread plays Marlin or Klipper on the
master end (checksums verified, numbered lines tracked, unnumbered safe-stop lines
recorded). Every fault case of issue 12 stops the job, says the line reached and, when
the link still works, leaves the printer with heaters off and the nozzle lifted."""
from __future__ import annotations

import os
import select
import threading
import time
import tty

import pytest
import serial

from calib.errors import UserError
from calib.sender import SAFE_STOP, checksum, numbered, send_gcode

FAST = dict(silence_timeout_s=0.5, boot_timeout_s=3.0, retry_s=0.3)
JOB = "\n".join(f"G1 X{i} Y{i} F3000 ; move {i}" for i in range(1, 21)) + "\n"


class FakePrinter(threading.Thread):
    """Marlin-like by default. Hooks: ``on_numbered(n, cmd) -> list[bytes] | None``
    (None: the normal 'ok'); ``boot_s`` of deafness before the banner; ``garbage`` only."""

    def __init__(self, on_numbered=None, boot_s=0.0, garbage=False, split_ok=False):
        super().__init__(daemon=True)
        self.master, slave = os.openpty()
        tty.setraw(slave)
        self.slave_name = os.ttyname(slave)
        self._slave = slave
        self.on_numbered = on_numbered or (lambda n, cmd: None)
        self.boot_until = time.monotonic() + boot_s if boot_s else 0.0
        self.booted = not boot_s
        self.garbage, self.split_ok = garbage, split_ok
        self.numbered: list[tuple[int, str]] = []
        self.plain: list[str] = []
        self.running = True
        self.start()

    def send(self, data: bytes):
        try:
            os.write(self.master, data)
        except OSError:
            pass

    def drop(self):
        self.running = False
        os.close(self.master)

    def run(self):
        buf = b""
        while self.running:
            if self.garbage:
                self.send(bytes([0xF0, 0x83, 0x11, 0xFE, 0x80, 0x9C, 0xE1, 0x05]))
            try:
                r, _, _ = select.select([self.master], [], [], 0.02)
                data = os.read(self.master, 4096) if r else b""
            except (OSError, ValueError):
                return
            if self.boot_until:
                if time.monotonic() < self.boot_until:
                    continue                       # deaf while booting: input lost
                self.boot_until = 0.0
                self.send(b"start\necho:Marlin 2.1.2\n")
                self.booted = True
                continue
            buf += data
            while b"\n" in buf:
                raw, buf = buf.split(b"\n", 1)
                self.handle(raw.decode().strip())

    def handle(self, line: str):
        if "*" not in line:
            self.plain.append(line)
            self.send(b"ok\n")
            return
        payload, cs = line.rsplit("*", 1)
        assert checksum(payload) == int(cs), line
        n, cmd = int(payload.split()[0][1:]), payload.split(" ", 1)[1]
        if cmd.startswith("M110"):
            self.send(b"ok\n")
            return
        reply = self.on_numbered(n, cmd)
        self.numbered.append((n, cmd))
        if reply is None:
            if self.split_ok:
                self.send(b"o")
                time.sleep(0.03)
                self.send(b"k\n")
            else:
                self.send(b"ok\n")
        else:
            for r in reply:
                if r == "DROP":
                    self.drop()
                    return
                if isinstance(r, float):
                    time.sleep(r)
                else:
                    self.send(r)


def _send(fake, **kw):
    port = serial.Serial(fake.slave_name, 115200, timeout=0.05)
    try:
        return send_gcode(port, JOB, **{**FAST, **kw})
    finally:
        fake.running = False
        port.close()


def test_checksum_matches_hand_computed_value():
    # XOR of the bytes of "N123 M104 S200", worked by hand: 0x67 = 103
    assert checksum("N123 M104 S200") == 103
    assert numbered(5, "G28") == "N5 G28*" + str(checksum("N5 G28"))


def test_a_clean_job_with_an_ok_split_across_reads():
    fake = FakePrinter(split_ok=True)
    rep = _send(fake)
    assert rep.lines_sent == 20 and [c for _, c in fake.numbered][-1] == "G1 X20 Y20 F3000"
    assert [n for n, _ in fake.numbered] == list(range(1, 21))


def test_heating_longer_than_the_silence_timeout_is_fine_while_reports_arrive():
    def on(n, cmd):
        if n == 2:           # an M109: 1.2 s of temperature reports (silence timeout 0.5 s)
            reports = [x for k in range(12) for x in (0.1, b" T:%.1f /210.0 B:60.0 /60.0\n" % (150 + 5 * k))]
            return reports + [b"ok\n"]
        return None
    rep = _send(FakePrinter(on))
    assert rep.lines_sent == 20


def test_silence_stops_the_job_and_sends_the_safe_stop():
    fake = FakePrinter(lambda n, cmd: [] if n == 3 else None)   # line 3 never answered
    with pytest.raises(UserError) as e:
        _send(fake)
    msg = str(e.value)
    assert "line 3 of 20" in msg and "no word from the printer" in msg
    assert "safe stop sent: M104 S0; M140 S0" in msg
    assert list(SAFE_STOP) == fake.plain[:len(SAFE_STOP)]


def test_resends_spread_over_a_job_are_recovered_but_one_line_failing_again_and_again_stops():
    asked = set()

    def every_fifth(n, cmd):
        if n % 5 == 0 and n not in asked:
            asked.add(n)
            return [b"Error:checksum mismatch, Last Line: %d\n" % (n - 1), b"Resend: %d\n" % n, b"ok\n"]
        return None
    rep = _send(FakePrinter(every_fifth))
    assert rep.resends == 4 and rep.lines_sent == 20
    bad = FakePrinter(lambda n, cmd: [b"Resend: 7\n", b"ok\n"] if n == 7 else None)
    with pytest.raises(UserError) as e:
        _send(bad)
    assert "line 7 was resent 5 times" in str(e.value) and "line 7 of 20" in str(e.value)


def test_a_board_reset_mid_job_stops_it_instead_of_resending_from_line_1():
    fake = FakePrinter(lambda n, cmd: [b"start\n", b"echo:Marlin 2.1.2\n"] if n == 6 else None)
    with pytest.raises(UserError) as e:
        _send(fake)
    assert "restarted" in str(e.value) and "line 6 of 20" in str(e.value)
    assert max(n for n, _ in fake.numbered) == 6 and [n for n, _ in fake.numbered].count(1) == 1
    lost = FakePrinter(lambda n, cmd: [b"Error:Line Number is not Last Line Number+1, Last Line: 0\n",
                                        b"Resend: 1\n", b"ok\n"] if n == 9 else None)
    with pytest.raises(UserError, match="asked for line 1 while line 9 was in flight"):
        _send(lost)


def test_klipper_errors_and_shutdown_stop_the_job():
    fake = FakePrinter(lambda n, cmd: [b"!! Move out of range: 300.000 0.000 0.200 [0.000]\n", b"ok\n"]
                       if n == 4 else None)
    with pytest.raises(UserError) as e:
        _send(fake)
    assert "Klipper reported: Move out of range" in str(e.value) and "line 4 of 20" in str(e.value)
    assert "M104 S0" in fake.plain and "G1 Z10 F600" in fake.plain
    down = FakePrinter(lambda n, cmd: [b"// Klipper state: Shutdown\n", b"ok\n"] if n == 2 else None)
    with pytest.raises(UserError, match="Klipper is not ready"):
        _send(down)


def test_a_dropped_connection_says_the_line_and_that_the_safe_stop_could_not_be_sent():
    fake = FakePrinter(lambda n, cmd: ["DROP"] if n == 5 else None)
    with pytest.raises(UserError) as e:
        _send(fake)
    msg = str(e.value)
    assert "line 5 of 20" in msg and "dropped" in msg and "could NOT be sent" in msg


def test_ctrl_c_sends_the_safe_stop_with_motors_off_when_asked():
    fake = FakePrinter()
    port = serial.Serial(fake.slave_name, 115200, timeout=0.05)

    def progress(done, total):
        if done == 3:
            raise KeyboardInterrupt
    with pytest.raises(UserError) as e:
        send_gcode(port, JOB, progress=progress, motors_off=True, **FAST)
    port.close()
    assert "interrupted (Ctrl-C)" in str(e.value) and "line 4 of 20" in str(e.value)
    assert fake.plain[-1] == "M84" and "M140 S0" in fake.plain


def test_a_booting_board_loses_no_command_and_a_wrong_baud_rate_is_named():
    fake = FakePrinter(boot_s=0.8)
    rep = _send(fake)
    assert rep.lines_sent == 20 and fake.numbered[0] == (1, "G1 X1 Y1 F3000")
    noisy = FakePrinter(garbage=True)
    with pytest.raises(UserError, match="wrong baud rate"):
        _send(noisy)
