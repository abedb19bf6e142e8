"""Stream G-code to a printer over a serial port (pyserial), the way host software does,
and leave the printer safe whatever goes wrong.

Protocol (Marlin/RRF/Klipper's serial emulation all accept it): each command is sent as
``N<line> <cmd>*<checksum>`` where the checksum is the XOR of every byte before ``*``;
the host waits for ``ok`` before the next line and honours ``Resend: <n>`` by rewinding.
Comments and blank lines are never sent.

What the link watches for (each is a :class:`LinkFault` that stops the job):
- silence: no byte at all for ``silence_timeout_s`` (temperature reports during M109,
  ``busy:`` keep-alives and ``echo:`` lines all count as signs of life; a long heat-up is
  not a fault);
- a line resent more than ``max_resends_per_line`` times (a bad cable), not a global
  count (51 recovered resends spread over a long job are fine);
- a reset: the firmware's ``start`` banner mid-job, or a resend request for a line
  before the one in flight (the board forgot where it was); the job is never re-sent
  from line 1 behind the user's back;
- errors: Marlin/RRF ``Error:`` (other than the checksum/line-number ones a resend
  answers), Klipper ``!!`` lines and ``// Klipper state: Shutdown``;
- the connection dropping (a pyserial or OS error while reading or writing);
- Ctrl-C.
On every fault the safe stop (:data:`SAFE_STOP`: heaters off, retract, lift; motors off
only if asked) is sent if the link still works, and the UserError says which line of the
job was reached and what was sent.

Start-up: the port opening resets most boards; the handshake sends ``M110 N0`` until the
firmware answers ``ok`` (up to ``boot_timeout_s``), so a board that is still booting loses
nothing; bytes that are not text mean a wrong baud rate, and the error says so. Reads
are buffered until a newline, so an ``ok`` split across two reads is one ``ok``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

from calib.errors import UserError

#: Sent, unnumbered, after any fault (Marlin, RRF and Klipper accept unnumbered lines).
SAFE_STOP = ("M104 S0", "M140 S0", "G91", "G1 E-2 F1800", "G1 Z10 F600", "G90")
MOTORS_OFF = "M84"


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


class LinkFault(Exception):
    """Why a job stopped (internal; turned into a UserError with the line reached)."""

    def __init__(self, why: str, alive: bool = True):
        super().__init__(why)
        self.alive = alive       # False: the link itself is gone, nothing more can be sent


@dataclass
class Link:
    """Line reader over a pyserial port (``write``, ``read``, ``in_waiting``) or any object
    with ``write(bytes)`` and ``readline() -> bytes`` (partial lines and b"" allowed)."""

    port: object
    buf: bytes = b""
    garbage: int = 0
    seen: int = 0
    log: list = field(default_factory=list)

    def write(self, text: str) -> None:
        try:
            self.port.write((text + "\n").encode("ascii", "replace"))
        except Exception as exc:          # pyserial raises SerialException/OSError on unplug
            raise LinkFault(f"the connection dropped while sending ({type(exc).__name__}: {exc})",
                            alive=False) from None

    def line(self) -> str | None:
        """One complete line, or None when nothing complete arrived within one port read."""
        if b"\n" not in self.buf:
            try:
                chunk = self._chunk()
            except Exception as exc:
                raise LinkFault(f"the connection dropped ({type(exc).__name__}: {exc})",
                                alive=False) from None
            if chunk:
                self.seen += len(chunk)
                self.garbage += sum(1 for b in chunk if not (32 <= b < 127 or b in (9, 10, 13)))
                self.buf += chunk
        if b"\n" not in self.buf:
            return None
        raw, self.buf = self.buf.split(b"\n", 1)
        text = raw.decode("ascii", "replace").strip()
        self.log.append(text)
        return text

    def _chunk(self) -> bytes:
        # Not port.readline(): on POSIX pyserial that is IOBase.readline, byte by byte with
        # no overall timeout, so a wrong-baud board streaming garbage without newlines
        # would hang the sender for ever. read() returns what is waiting, or waits at
        # most the port's timeout for one byte.
        p = self.port
        if hasattr(p, "in_waiting") and hasattr(p, "read"):
            n = p.in_waiting
            return p.read(n if n else 1)
        return p.readline()

    def looks_like_wrong_baud(self) -> bool:
        return self.seen >= 8 and self.garbage > 0.3 * self.seen


def _fault_in(line: str) -> str | None:
    low = line.lower()
    if line.startswith("!!"):
        return f"Klipper reported: {line[2:].strip()}"
    if low.startswith("// klipper state: shutdown") or low.startswith("// klipper state: disconnect"):
        return f"Klipper is not ready: {line[2:].strip()}"
    if low.startswith("error") and not any(k in low for k in ("resend", "checksum", "line number",
                                                               "last line", "no line number")):
        return f"the printer reported: {line}"
    return None


def _resend_target(line: str) -> int | None:
    low = line.lower()
    if low.startswith("resend:") or low.startswith("rs "):
        try:
            return int(line.split(":", 1)[-1].split()[-1].lstrip("Nn"))
        except ValueError:
            return None
    return None


def _wait_ok(link: Link, silence_timeout_s: float, expect_banner_ok: bool = False):
    """Read until ``ok``; return None or the line the printer wants resent. Any line at all
    restarts the silence clock. A ``start`` banner is a reset (LinkFault)."""
    last = time.monotonic()
    resend = None
    while True:
        line = link.line()
        if line is None:
            if link.looks_like_wrong_baud():
                raise LinkFault("the printer sends unreadable bytes: wrong baud rate? (Marlin "
                                "boards use 115200 or 250000; set it with --baud)")
            if time.monotonic() - last > silence_timeout_s:
                raise LinkFault(f"no word from the printer for {silence_timeout_s:.0f} s")
            continue
        last = time.monotonic()
        if not line:
            continue
        why = _fault_in(line)
        if why:
            raise LinkFault(why)
        if line.lower() == "start" and not expect_banner_ok:
            raise LinkFault("the printer restarted (it printed its 'start' banner): the board "
                            "reset, so the job cannot continue where it was")
        r = _resend_target(line)
        if r is not None:
            resend = r
        elif line.lower().startswith("ok"):
            return resend


def handshake(link: Link, boot_timeout_s: float = 20.0, retry_s: float = 2.0) -> None:
    """``M110 N0`` until the firmware answers ``ok``: waits out a board that is booting
    (the port opening resets most of them) instead of losing the first command."""
    t0 = time.monotonic()
    while True:
        link.write(numbered(0, "M110 N0"))
        try:
            if _wait_ok(link, retry_s, expect_banner_ok=True) is None:
                return
        except LinkFault as exc:
            if not str(exc).startswith("no word") or time.monotonic() - t0 > boot_timeout_s:
                raise
        if time.monotonic() - t0 > boot_timeout_s:
            raise LinkFault(f"no answer to M110 within {boot_timeout_s:.0f} s: is the printer on, "
                            "and is this its port?")


def safe_stop(link: Link, motors_off: bool = False, ack_timeout_s: float = 2.0) -> list[str]:
    """Send :data:`SAFE_STOP` (and M84 if asked), unnumbered, one line per ``ok`` (a
    firmware's small receive buffer drops lines sent back to back), waiting at most
    ``ack_timeout_s`` for all acknowledgements together; returns what was sent."""
    sent = []
    deadline = time.monotonic() + ack_timeout_s   # one budget: a dead link costs 2 s, not 12
    for cmd in SAFE_STOP + ((MOTORS_OFF,) if motors_off else ()):
        try:
            link.write(cmd)
            while time.monotonic() < deadline:
                line = link.line()
                if line is not None and line.lower().startswith("ok"):
                    break
        except LinkFault:
            break
        sent.append(cmd)
    return sent


def send_gcode(port, text: str, *, silence_timeout_s: float = 60.0, max_resends_per_line: int = 5,
               boot_timeout_s: float = 20.0, retry_s: float = 2.0, motors_off: bool = False,
               progress=None) -> SendReport:
    """Send ``text`` line by line over an open pyserial-like ``port`` (see module docstring).

    ``progress`` is an optional callable(n_done, n_total). On any fault the safe stop is
    sent and a UserError says the line reached (1-based among the commands sent), what
    went wrong and what was sent."""
    commands = [c for c in (strip_comment(ln) for ln in text.splitlines()) if c]
    t0 = time.monotonic()
    link = Link(port)
    i, resends = 0, 0
    per_line: dict[int, int] = {}
    try:
        handshake(link, boot_timeout_s, retry_s)
        while i < len(commands):
            link.write(numbered(i + 1, commands[i]))
            want = _wait_ok(link, silence_timeout_s)
            if want is not None:              # resend request
                if want < i + 1 - 1 or want > i + 1:
                    raise LinkFault(f"the printer asked for line {want} while line {i + 1} was in "
                                    "flight: it reset or lost lines")
                resends += 1
                per_line[want] = per_line.get(want, 0) + 1
                if per_line[want] > max_resends_per_line:
                    raise LinkFault(f"line {want} was resent {max_resends_per_line} times: check the "
                                    "USB cable (short, shielded) and the baud rate")
                i = want - 1
                continue
            i += 1
            if progress:
                progress(i, len(commands))
    except (LinkFault, KeyboardInterrupt) as exc:
        alive = not isinstance(exc, LinkFault) or exc.alive
        why = "interrupted (Ctrl-C)" if isinstance(exc, KeyboardInterrupt) else str(exc)
        sent = safe_stop(link, motors_off) if alive else []
        where = (f"line {i + 1} of {len(commands)} ({commands[i]})" if i < len(commands)
                 else f"the end ({len(commands)} lines)")
        stop = (f"safe stop sent: {'; '.join(sent)}" if sent else
                "the safe stop could NOT be sent: switch the printer off or cut its heaters now")
        raise UserError(f"printing stopped at {where}: {why}; {stop}") from None
    return SendReport(lines_sent=len(commands), resends=resends, seconds=time.monotonic() - t0)


def open_port(device: str, baud: int = 115200):
    """Open a serial port (a device path, or a pyserial URL such as ``loop://``). No fixed
    sleep: :func:`handshake` waits for the firmware to answer."""
    import serial  # pyserial

    try:
        return serial.serial_for_url(device, baudrate=baud, timeout=0.2)
    except (serial.SerialException, ValueError) as exc:
        raise UserError(f"cannot open serial port {device}: {exc}") from None
