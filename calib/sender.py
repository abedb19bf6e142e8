"""Stream G-code to a printer over a serial port (pyserial), the way host software does.

Protocol (Marlin/RRF/Klipper's serial emulation all accept it): each command is sent as
``N<line> <cmd>*<checksum>`` where the checksum is the XOR of every byte before ``*``;
the host waits for ``ok`` before the next line and honours ``Resend: <n>`` by rewinding.
Comments and blank lines are never sent. ``busy:`` / ``echo:`` lines are ignored.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

from calib.errors import UserError


def strip_comment(line: str) -> str:
    """G-code without its ``;`` comment and surrounding blanks."""
    return line.split(";", 1)[0].strip()


def checksum(payload: str) -> int:
    """XOR of all bytes of ``payload`` (RepRap numbered-line checksum)."""
    cs = 0
    for b in payload.encode("ascii", "replace"):
        cs ^= b
    return cs


def numbered(line_no: int, cmd: str) -> str:
    payload = f"N{line_no} {cmd}"
    return f"{payload}*{checksum(payload)}"


@dataclass
class SendReport:
    lines_sent: int
    resends: int
    seconds: float


def send_gcode(port, text: str, *, timeout_s: float = 120.0, progress=None) -> SendReport:
    """Send ``text`` line by line over an open pyserial-like ``port``.

    ``port`` needs ``write(bytes)`` and ``readline() -> bytes``. ``progress`` is an
    optional callable(n_done, n_total). Raises UserError on a printer error or timeout.
    """
    commands = [c for c in (strip_comment(ln) for ln in text.splitlines()) if c]
    t0 = time.monotonic()
    # M110 resets the printer's line counter so our numbering starts at 1.
    port.write((numbered(0, "M110 N0") + "\n").encode())
    _wait_ok(port, timeout_s)
    i, resends = 0, 0
    while i < len(commands):
        port.write((numbered(i + 1, commands[i]) + "\n").encode())
        reply = _wait_ok(port, timeout_s)
        if reply is not None:  # resend request: rewind to the asked line
            resends += 1
            if resends > 50:
                raise UserError("printer asked for more than 50 resends: check the cable and baud rate")
            i = max(0, reply - 1)
            continue
        i += 1
        if progress:
            progress(i, len(commands))
    return SendReport(lines_sent=len(commands), resends=resends, seconds=time.monotonic() - t0)


def _wait_ok(port, timeout_s: float):
    """Read until ``ok``; return None, or the line number the printer wants resent."""
    deadline = time.monotonic() + timeout_s
    resend = None
    while time.monotonic() < deadline:
        raw = port.readline()
        if not raw:
            continue
        line = raw.decode("ascii", "replace").strip()
        low = line.lower()
        if low.startswith("resend:") or low.startswith("rs "):
            try:
                resend = int(line.split(":", 1)[-1].split()[-1].lstrip("N"))
            except ValueError:
                resend = None
        elif low.startswith("ok"):
            return resend
        elif low.startswith("error") and "resend" not in low and "checksum" not in low \
                and "line number" not in low:
            raise UserError(f"printer reported an error: {line}")
    raise UserError(f"no 'ok' from the printer within {timeout_s:.0f} s: is it connected and on?")


def open_port(device: str, baud: int = 115200):
    """Open a serial port (a device path, or a pyserial URL such as ``loop://``)."""
    import serial  # pyserial

    try:
        port = serial.serial_for_url(device, baudrate=baud, timeout=1.0)
    except (serial.SerialException, ValueError) as exc:
        raise UserError(f"cannot open serial port {device}: {exc}") from None
    # Printers reset when the port opens; give the bootloader time and drain the banner.
    if not device.startswith(("loop://", "socket://", "rfc2217://")):
        time.sleep(2.0)
        port.reset_input_buffer()
    return port
