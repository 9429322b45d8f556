"""The camera tower's stepper controller: ASCII lines with a checksum, both directions.

Every line is ``BODY*CC\\n``: ``BODY`` printable ASCII words separated by single spaces,
``CC`` the XOR of all bytes of ``BODY`` as two upper-case hex digits (as in NMEA 0183), at most
``MAX_LINE`` bytes before the newline; a ``\\r`` before the newline is ignored. Positions are
signed integers in microsteps of the tower (``steps_per_rev`` = full steps × microsteps × gear
ratio, e.g. 200 × 16 × 2 = 6400); position 0 is the reference trigger's rising edge once homed.

Host -> controller::

    PING                 keep-alive; answered with PONG
    POS                  answered with POS
    HOME                 turn forward (+) until the reference trigger's rising edge; ACK HOME,
                         later HOMED or ERR NOTRIGGER (no edge within one turn plus the slot)
    MOVE <steps>         go to an absolute position; ACK MOVE, later DONE or ERR POSITION
                         (or ERR NOTHOMED / ERR BUSY / ERR RANGE at once instead of ACK)
    STOP                 stop where it is, coils held; ACK STOP

Controller -> host::

    PONG <pos> <state>
    POS <pos> <target> <state>
    ACK <command>                       HOME, MOVE or STOP
    HOMED <count>                       trigger fired at this count (from power-up or the
                                        last home); the position is now 0
    DONE <pos>                          a MOVE reached its target
    TIMEOUT <pos>                       the host was silent for the controller's timeout: it
                                        stopped and de-energised the coils (state UNHOMED)
    ERR <code> <value>                  NOTRIGGER <steps turned>, POSITION <count where the
                                        trigger disagreed with the count>, NOTHOMED 0,
                                        BUSY 0, RANGE <steps>, BADCMD 0

``state`` is one of ``UNHOMED HOMING READY MOVING``. The controller checks the trigger at
every step it makes: the trigger is lit exactly where the count is within the slot (0 up to
the slot width, modulo a turn), so lost steps show as a disagreement; it then stops, reports
ERR POSITION and wants a HOME before it moves again. Any valid host line resets its silence
timer; a host line that fails its checksum is answered with ERR BADCMD and otherwise ignored.
"""

from __future__ import annotations

from dataclasses import dataclass

MAX_LINE = 64
STATES = ("UNHOMED", "HOMING", "READY", "MOVING")
COMMANDS = ("PING", "POS", "HOME", "MOVE", "STOP")
ERROR_CODES = ("NOTRIGGER", "POSITION", "NOTHOMED", "BUSY", "RANGE", "BADCMD")
# reply word -> its fields: "i" an integer, "s" a state, "c" an error code, "k" a command
REPLIES = {"PONG": "is", "POS": "iis", "ACK": "k", "HOMED": "i", "DONE": "i", "TIMEOUT": "i",
           "ERR": "ci"}


class TowerProtocolError(ValueError):
    """A line from (or to) the tower controller that cannot be used."""

    user_error = True


def checksum(body: bytes) -> int:
    c = 0
    for b in body:
        c ^= b
    return c


def encode(*words: str | int) -> bytes:
    """One line: the words joined by spaces, with its checksum and newline."""
    body = " ".join(str(w) for w in words).encode("ascii")
    if len(body) + 3 > MAX_LINE:
        raise TowerProtocolError(f"line of {len(body) + 3} bytes, at most {MAX_LINE}")
    return body + b"*%02X\n" % checksum(body)


def split(line: bytes) -> list[str]:
    """The words of one line (without its newline), after checking its framing and checksum."""
    if line.endswith(b"\r"):
        line = line[:-1]
    if len(line) > MAX_LINE:
        raise TowerProtocolError(f"line of {len(line)} bytes, at most {MAX_LINE}")
    body, star, cc = line.rpartition(b"*")
    if not star:
        raise TowerProtocolError(f"line {line[:20]!r} has no checksum")
    if len(cc) != 2 or not all(c in b"0123456789ABCDEF" for c in cc):
        raise TowerProtocolError(f"checksum {cc[:8]!r} is not two upper-case hex digits")
    if int(cc, 16) != checksum(body):
        raise TowerProtocolError(f"checksum {cc.decode()} does not match "
                                 f"{checksum(body):02X} of {body[:20]!r}")
    if not body or not all(0x21 <= b <= 0x7E or b == 0x20 for b in body):
        raise TowerProtocolError(f"line {body[:20]!r} is empty or not printable ASCII")
    words = body.decode("ascii").split(" ")
    if "" in words:
        raise TowerProtocolError(f"line {body[:20]!r} has an empty word")
    return words


def _integer(word: str) -> int:
    digits = word[1:] if word.startswith("-") else word
    if not digits.isdigit() or not digits.isascii() or len(digits) > 10:
        raise TowerProtocolError(f"{word!r} is not an integer")
    return int(word)


@dataclass(frozen=True)
class Reply:
    kind: str                       # a key of REPLIES
    ints: tuple[int, ...] = ()      # its integer fields in order
    word: str = ""                  # its state, error code or acknowledged command


def parse_reply(line: bytes) -> Reply:
    """A controller line (without the newline) as a Reply; TowerProtocolError if it is not one
    exactly (framing, checksum, unknown kind, number or kind of fields)."""
    words = split(line)
    kind, fields = words[0], words[1:]
    schema = REPLIES.get(kind)
    if schema is None:
        raise TowerProtocolError(f"unknown reply {kind[:16]!r}")
    if len(fields) != len(schema):
        raise TowerProtocolError(f"{kind} with {len(fields)} fields, expected {len(schema)}")
    ints: list[int] = []
    word = ""
    for f, t in zip(fields, schema, strict=True):
        if t == "i":
            ints.append(_integer(f))
            continue
        allowed = {"s": STATES, "c": ERROR_CODES, "k": COMMANDS}[t]
        if f not in allowed:
            raise TowerProtocolError(f"{kind}: {f[:16]!r} is not one of {' '.join(allowed)}")
        word = f
    return Reply(kind, tuple(ints), word)


def parse_command(line: bytes) -> tuple[str, int | None]:
    """A host line as (command, argument); TowerProtocolError if it is not one exactly."""
    words = split(line)
    cmd, args = words[0], words[1:]
    if cmd not in COMMANDS:
        raise TowerProtocolError(f"unknown command {cmd[:16]!r}")
    want = 1 if cmd == "MOVE" else 0
    if len(args) != want:
        raise TowerProtocolError(f"{cmd} with {len(args)} arguments, expected {want}")
    return cmd, (_integer(args[0]) if args else None)


class LineSplitter:
    """Lines out of a byte stream; a run of more than ``MAX_LINE`` bytes without a newline is
    dropped (and counted) up to the next newline."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self._discarding = False
        self.overlong = 0

    def feed(self, data: bytes) -> list[bytes]:
        self._buf += data
        out: list[bytes] = []
        while True:
            i = self._buf.find(b"\n")
            if i < 0:
                if len(self._buf) > MAX_LINE + 1:
                    if not self._discarding:
                        self.overlong += 1
                    self._discarding = True
                    self._buf.clear()
                return out
            line = bytes(self._buf[:i])
            del self._buf[:i + 1]
            if self._discarding:
                self._discarding = False
                continue
            out.append(line)
