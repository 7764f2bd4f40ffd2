"""A loopback WSG-50 protocol server (thread) for the gripper tests; the fingers follow commands instantly."""

from __future__ import annotations

import socket
import struct
import threading

from umi_aug.deploy.wsg50 import PREAMBLE, Status, crc16, decode_stream, encode_message
from umi_aug.errors import DeployError


class FakeWSG:
    def __init__(self, unknown_script: bool = False, corrupt_replies: bool = False) -> None:
        self.srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.srv.bind(("127.0.0.1", 0))
        self.srv.listen(1)
        self.port = self.srv.getsockname()[1]
        self.position = 20.0  # mm
        self.received: list[tuple[int, bytes]] = []  # (command id, payload) of valid frames
        self.bad_crc = 0
        self.unknown_script, self.corrupt_replies = unknown_script, corrupt_replies
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _reply(self, conn, cmd: int, status: int, params: bytes = b"") -> None:
        msg = bytearray(b"\x00\x13" + encode_message(cmd, struct.pack("<H", status) + params))  # junk first
        if self.corrupt_replies:
            msg[-3] ^= 0x01
        for i in range(0, len(msg), 3):  # split across TCP segments
            conn.sendall(bytes(msg[i:i + 3]))

    def _state(self) -> bytes:
        return bytes([0]) + struct.pack("<4f", self.position, 0.0, 1.5, 12.0)

    def _serve(self) -> None:
        conn, _ = self.srv.accept()
        buf = bytearray()

        def recv_exact(n):
            while len(buf) < n:
                chunk = conn.recv(4096)
                if not chunk:
                    raise ConnectionError
                buf.extend(chunk)
            out = bytes(buf[:n])
            del buf[:n]
            return out

        try:
            while True:
                try:
                    cmd, payload = decode_stream(recv_exact)
                except DeployError:  # bad CRC: the WSG answers E_CHECKSUM_ERROR
                    self.bad_crc += 1
                    self._reply(conn, 0x00, Status.E_CHECKSUM_ERROR)
                    continue
                self.received.append((cmd, payload))
                if cmd == 0x20:
                    self._reply(conn, cmd, Status.E_CMD_PENDING)
                    self.position = 110.0
                    self._reply(conn, cmd, Status.E_SUCCESS)
                elif cmd == 0x21:
                    flag, width, speed = struct.unpack("<Bff", payload)
                    if not 0 <= width <= 110:
                        self._reply(conn, cmd, Status.E_RANGE_ERROR)
                    else:
                        self.position = width
                        self._reply(conn, cmd, Status.E_SUCCESS)
                elif cmd in (0xB0, 0xB1):
                    if self.unknown_script:
                        self._reply(conn, cmd, Status.E_CMD_UNKNOWN)
                        continue
                    if cmd == 0xB1:
                        self.position = struct.unpack("<6f", payload[1:])[0]
                    self._reply(conn, cmd, Status.E_SUCCESS, self._state())
                elif cmd in (0x22, 0x24):
                    self._reply(conn, cmd, Status.E_SUCCESS)
                elif cmd == 0x07:
                    break
                else:
                    self._reply(conn, cmd, Status.E_CMD_UNKNOWN)
        except (ConnectionError, OSError):
            pass
        finally:
            conn.close()
            self.srv.close()

    def ids(self) -> list[int]:
        return [c for c, _ in self.received]


def crc16_reference(data: bytes, crc: int = 0xFFFF) -> int:
    """Table-free computation of the same CRC (the table entry is derived bit by bit for every byte)."""
    for b in data:
        c = ((crc ^ b) & 0xFF) << 8
        for _ in range(8):
            c = ((c << 1) ^ 0x1021) & 0xFFFF if c & 0x8000 else (c << 1) & 0xFFFF
        crc = c ^ (crc >> 8)
    return crc


__all__ = ["FakeWSG", "crc16_reference", "PREAMBLE", "crc16"]
