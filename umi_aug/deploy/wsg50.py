"""Weiss WSG-50 gripper over its binary TCP protocol (UMI's ``wsg_binary_driver`` + ``wsg_controller``).

Frame (both directions): ``0xAA 0xAA 0xAA | command id (u8) | payload length (u16 LE) | payload | CRC16 (u16 LE)``;
the CRC (CCITT polynomial 0x1021, table-driven in the WSG's byte order, initial value 0xFFFF) covers everything
before it, so the CRC over a whole valid frame is 0. Responses start their payload with a u16 LE status code.

Position control uses UMI's gripper-side Lua script (``cmd_measure.lua``, which must run on the WSG): command
0xB0 = measure, 0xB1 = position PD (position mm, velocity mm/s, kp, kd, travel / blocked force limit N). Each
returns ``state (u8) + 4 × f32``: position (mm), velocity (mm/s), motor force (N), gripper timestamp (s).
The public API is in metres.
"""

from __future__ import annotations

import enum
import logging
import socket
import struct
from dataclasses import dataclass
from typing import Any, Mapping

from umi_aug.config_check import reject_unknown_keys
from umi_aug.deploy.device_process import child_setup
from umi_aug.deploy.gripper_process import GripperProcess, run_gripper_loop
from umi_aug.deploy.shared_state import SharedStateBuffer
from umi_aug.errors import DeployError

__all__ = ["crc16", "encode_message", "decode_stream", "Status", "WSG50Driver", "WSGConfig", "WSG50Gripper"]

log = logging.getLogger(__name__)

PREAMBLE = b"\xaa\xaa\xaa"
CMD_DISCONNECT, CMD_HOMING, CMD_PREPOSITION, CMD_STOP, CMD_ACK_FAULT = 0x07, 0x20, 0x21, 0x22, 0x24
CMD_SCRIPT_MEASURE, CMD_SCRIPT_POSITION_PD = 0xB0, 0xB1


def _crc_table() -> list[int]:
    table = []
    for i in range(256):
        c = i << 8
        for _ in range(8):
            c = ((c << 1) ^ 0x1021) if c & 0x8000 else (c << 1)
        table.append(c & 0xFFFF)
    return table


_TABLE = _crc_table()


def crc16(data: bytes, crc: int = 0xFFFF) -> int:
    """The WSG's CRC16 of ``data`` continuing from ``crc``."""
    for b in data:
        crc = _TABLE[(crc ^ b) & 0xFF] ^ (crc >> 8)
    return crc


class Status(enum.IntEnum):
    """WSG status codes (first two payload bytes of every response)."""

    E_SUCCESS = 0
    E_NOT_AVAILABLE = 1
    E_NO_SENSOR = 2
    E_NOT_INITIALIZED = 3
    E_ALREADY_RUNNING = 4
    E_FEATURE_NOT_SUPPORTED = 5
    E_INCONSISTENT_DATA = 6
    E_TIMEOUT = 7
    E_READ_ERROR = 8
    E_WRITE_ERROR = 9
    E_INSUFFICIENT_RESOURCES = 10
    E_CHECKSUM_ERROR = 11
    E_NO_PARAM_EXPECTED = 12
    E_NOT_ENOUGH_PARAMS = 13
    E_CMD_UNKNOWN = 14
    E_CMD_FORMAT_ERROR = 15
    E_ACCESS_DENIED = 16
    E_ALREADY_OPEN = 17
    E_CMD_FAILED = 18
    E_CMD_ABORTED = 19
    E_INVALID_HANDLE = 20
    E_NOT_FOUND = 21
    E_NOT_OPEN = 22
    E_IO_ERROR = 23
    E_INVALID_PARAMETER = 24
    E_INDEX_OUT_OF_BOUNDS = 25
    E_CMD_PENDING = 26
    E_OVERRUN = 27
    E_RANGE_ERROR = 28
    E_AXIS_BLOCKED = 29
    E_FILE_EXIST = 30


def encode_message(cmd_id: int, payload: bytes = b"") -> bytes:
    """One framed message (preamble, id, length, payload, CRC)."""
    if not 0 <= cmd_id <= 0xFF or len(payload) > 0xFFFF:
        raise DeployError(f"WSG message: command id {cmd_id} must be a byte and payload <= 65535 bytes")
    body = PREAMBLE + bytes([cmd_id]) + struct.pack("<H", len(payload)) + payload
    return body + struct.pack("<H", crc16(body))


def decode_stream(recv_exact) -> tuple[int, bytes]:
    """Read one frame with ``recv_exact(n) -> bytes``; skip bytes until three 0xAA; check the CRC.

    Returns ``(command id, payload)``. Raises :class:`DeployError` on a CRC mismatch."""
    run = 0
    while run < 3:
        run = run + 1 if recv_exact(1) == b"\xaa" else 0
    head = recv_exact(3)
    (size,) = struct.unpack("<H", head[1:3])
    payload = recv_exact(size)
    tail = recv_exact(2)
    if crc16(PREAMBLE + head + payload + tail) != 0:
        raise DeployError(f"WSG: corrupted frame (CRC mismatch) for command 0x{head[0]:02X}")
    return head[0], payload


def _floats(*xs: float) -> bytes:
    return struct.pack(f"<{len(xs)}f", *xs)


class WSG50Driver:
    """Blocking client of one WSG-50 (``host:port``, default port 1000). Units at this level: mm, mm/s, N."""

    def __init__(self, host: str, port: int = 1000, timeout_s: float = 2.0) -> None:
        self.host, self.port, self.timeout_s = host, int(port), timeout_s
        self.sock: socket.socket | None = None

    def connect(self) -> None:
        try:
            self.sock = socket.create_connection((self.host, self.port), timeout=self.timeout_s)
        except OSError as exc:
            raise DeployError(f"WSG-50 at {self.host}:{self.port}: cannot connect ({exc})") from exc

    def _recv_exact(self, n: int) -> bytes:
        assert self.sock is not None
        buf = b""
        while len(buf) < n:
            try:
                chunk = self.sock.recv(n - len(buf))
            except OSError as exc:
                raise DeployError(f"WSG-50 at {self.host}:{self.port}: receive failed ({exc})") from exc
            if not chunk:
                raise DeployError(f"WSG-50 at {self.host}:{self.port}: connection closed")
            buf += chunk
        return buf

    def send(self, cmd_id: int, payload: bytes = b"") -> None:
        if self.sock is None:
            raise DeployError("WSG-50: not connected")
        try:
            self.sock.sendall(encode_message(cmd_id, payload))
        except OSError as exc:
            raise DeployError(f"WSG-50 at {self.host}:{self.port}: send failed ({exc})") from exc

    def command(self, cmd_id: int, payload: bytes = b"", wait: bool = True) -> bytes:
        """Send a command, read its response (skipping other commands' ones; waiting out E_CMD_PENDING when
        ``wait``); return the response parameters. A non-success status raises :class:`DeployError`."""
        self.send(cmd_id, payload)
        while True:
            rid, data = decode_stream(self._recv_exact)
            if rid != cmd_id:
                continue
            status = struct.unpack("<H", data[:2])[0] if len(data) >= 2 else -1
            if wait and status == Status.E_CMD_PENDING:
                continue
            if status not in (Status.E_SUCCESS, Status.E_CMD_PENDING):
                name = Status(status).name if status in Status._value2member_map_ else str(status)
                hint = " (is cmd_measure.lua running on the gripper?)" if status == Status.E_CMD_UNKNOWN else ""
                raise DeployError(f"WSG-50 command 0x{cmd_id:02X} failed: {name}{hint}")
            return data[2:]

    # ---------------------------------------------------------------- commands
    def ack_fault(self) -> None:
        self.command(CMD_ACK_FAULT, b"ack")

    def homing(self, positive: bool = True) -> None:
        self.command(CMD_HOMING, bytes([1 if positive else 2]))

    def pre_position(self, width_mm: float, speed_mm_s: float, clamp_on_block: bool = True) -> None:
        self.command(CMD_PREPOSITION, bytes([0 if clamp_on_block else 1]) + _floats(width_mm, speed_mm_s))

    def _script(self, cmd_id: int, *args: float) -> dict[str, float]:
        data = self.command(cmd_id, b"\x00" + _floats(*args), wait=False)
        if len(data) != 17:
            raise DeployError(f"WSG-50 script command 0x{cmd_id:02X}: reply of {len(data)} bytes, expected 17")
        pos, vel, force, t = struct.unpack("<4f", data[1:])
        return {"state": data[0], "position": pos, "velocity": vel, "force": force, "gripper_time": t}

    def measure(self) -> dict[str, float]:
        """Position (mm), velocity (mm/s), motor force (N) through the Lua script's 0xB0."""
        return self._script(CMD_SCRIPT_MEASURE)

    def position_pd(self, position_mm: float, velocity_mm_s: float, kp: float = 15.0, kd: float = 1e-3,
                    force_limit_n: float = 80.0) -> dict[str, float]:
        """Track ``position_mm`` with feed-forward ``velocity_mm_s`` (UMI's 0xB1 gains and 80 N limit)."""
        return self._script(CMD_SCRIPT_POSITION_PD, position_mm, velocity_mm_s, kp, kd, force_limit_n, force_limit_n)

    def close(self, stop_fingers: bool = True) -> None:
        """Stop the fingers (reply read; skipped when ``stop_fingers`` is False: nothing was commanded), say
        goodbye (0x07, no reply), close the socket; never raises."""
        if self.sock is None:
            return
        steps = [(CMD_STOP, lambda: self.command(CMD_STOP, wait=False))] if stop_fingers else []
        for cmd, fn in steps + [(CMD_DISCONNECT, lambda: self.send(CMD_DISCONNECT))]:
            try:
                fn()
            except DeployError as exc:
                log.error("WSG-50 close (command 0x%02X): %s", cmd, exc)
        self.sock.close()
        self.sock = None


@dataclass
class WSGConfig:
    """The ``gripper:`` block of a robot config (metres / seconds)."""

    gripper_ip: str = "192.168.0.18"
    gripper_port: int = 1000
    obs_latency: float = 0.01
    action_latency: float = 0.1
    frequency: float = 30.0
    max_speed: float = 0.2
    home_to_open: bool = True

    @classmethod
    def from_mapping(cls, m: Mapping[str, Any], where: str = "gripper") -> "WSGConfig":
        reject_unknown_keys(m, cls.__dataclass_fields__, where, DeployError)
        c = cls(**dict(m))
        if not (0 < c.frequency <= 100 and c.max_speed > 0):
            raise DeployError(f"{where}: frequency must be in (0, 100] Hz and max_speed > 0, got {c.frequency}, "
                              f"{c.max_speed}")
        return c


def _gripper_main(cfg: WSGConfig, commands: Any, state: SharedStateBuffer, stop_event: Any, errors: Any,
                  enabled: Any, parent_pid: int) -> None:
    child_setup(parent_pid)
    drv = WSG50Driver(cfg.gripper_ip, cfg.gripper_port)
    try:
        drv.connect()
        run_gripper_loop(drv, cfg, commands, state, stop_event, enabled, parent_pid)
    except BaseException as exc:  # noqa: BLE001 - reported to the runner
        errors.put(str(exc))
    finally:
        drv.close(stop_fingers=bool(enabled.value))  # observe-only: no command, only the goodbye


class WSG50Gripper(GripperProcess):
    """:class:`~umi_aug.deploy.interfaces.GripperInterface` for a WSG-50 (own process, ``frequency`` Hz): its
    client (:class:`WSG50Driver`) driven by :func:`~umi_aug.deploy.gripper_process.run_gripper_loop` behind the
    shared host side (:class:`~umi_aug.deploy.gripper_process.GripperProcess`)."""

    process_main = staticmethod(_gripper_main)

    def __init__(self, cfg: WSGConfig, ctx: Any = None, connect_timeout_s: float = 10.0) -> None:
        super().__init__(cfg, f"gripper WSG-50 {cfg.gripper_ip}:{cfg.gripper_port}", ctx, connect_timeout_s)
