"""Serial streaming protocol against a fake Marlin that checks checksums and asks for resends."""
import pytest

from calib.errors import UserError
from calib.sender import checksum, numbered, send_gcode


class FakeMarlin:
    """Accepts numbered lines, verifies the checksum, asks once for a resend of line 3."""

    def __init__(self, fail_line=3, error=None):
        self.received = []
        self.out = []
        self.fail_line = fail_line
        self.failed = False
        self.error = error

    def write(self, data: bytes):
        line = data.decode().strip()
        payload, cs = line.rsplit("*", 1)
        assert checksum(payload) == int(cs), line
        n = int(payload.split()[0][1:])
        cmd = payload.split(" ", 1)[1]
        if n == self.fail_line and not self.failed:
            self.failed = True
            self.out += [b"Error:checksum mismatch, Last Line: 2\n", f"Resend: {n}\n".encode(), b"ok\n"]
            return
        if self.error and cmd.startswith(self.error):
            self.out += [b"Error:Printer halted. kill() called!\n"]
            return
        if n > 0:
            self.received.append(cmd)
        self.out += [b"echo:busy: processing\n", b"ok\n"]

    def readline(self) -> bytes:
        return self.out.pop(0) if self.out else b""


def test_checksum_matches_hand_computed_value():
    # XOR of the bytes of "N123 M104 S200", worked by hand: 0x67 = 103
    assert checksum("N123 M104 S200") == 103
    assert numbered(123, "M104 S200") == "N123 M104 S200*103"


def test_send_strips_comments_and_honours_resend():
    port = FakeMarlin()
    text = "; header\nG28 ; home\n\nG1 X10 Y10 F3000\nG1 X20 E1\nM400\n"
    rep = send_gcode(port, text, timeout_s=1)
    assert port.received == ["G28", "G1 X10 Y10 F3000", "G1 X20 E1", "M400"]
    assert rep.resends == 1 and rep.lines_sent == 4


def test_printer_error_is_one_clear_line():
    port = FakeMarlin(fail_line=-1, error="M112")
    with pytest.raises(UserError, match="printer reported an error"):
        send_gcode(port, "G28\nM112\n", timeout_s=1)
