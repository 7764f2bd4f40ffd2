"""(c) the WSG-50 binary protocol against a local loopback protocol server."""

from __future__ import annotations

import struct
import time

import numpy as np
import pytest

from tests.deploy.wsg_server import PREAMBLE, FakeWSG, crc16_reference
from umi_aug.deploy.wsg50 import WSG50Driver, WSG50Gripper, WSGConfig, crc16, decode_stream, encode_message
from umi_aug.errors import DeployError
from umi_aug.deploy.safety import SafetyStop


def test_crc_matches_reference_and_frames_check_to_zero(rng):
    for n in (0, 1, 7, 300):
        data = rng.integers(0, 256, n).astype(np.uint8).tobytes()
        assert crc16(data) == crc16_reference(data)
    assert crc16(PREAMBLE) == 0x50F5  # the header constant UMI's receiver starts from
    msg = encode_message(0x20, b"\x01")
    assert msg[:7] == b"\xaa\xaa\xaa\x20\x01\x00\x01"
    assert struct.unpack("<H", msg[7:])[0] == crc16_reference(msg[:7]) and crc16(msg) == 0
    it = iter([b"\x00", b"\xaa", b"\x05"] + [bytes([b]) for b in msg])  # junk, a lone 0xAA, then the frame
    buf = b"".join(it)
    pos = [0]

    def recv_exact(k):
        out = buf[pos[0]:pos[0] + k]
        pos[0] += k
        return out

    assert decode_stream(recv_exact) == (0x20, b"\x01")
    bad = bytearray(msg)
    bad[6] ^= 0x40
    pos[0], buf = 0, bytes(bad)
    with pytest.raises(DeployError, match="CRC mismatch"):
        decode_stream(recv_exact)


def test_driver_commands_against_server():
    srv = FakeWSG()
    d = WSG50Driver("127.0.0.1", srv.port)
    d.connect()
    try:
        d.ack_fault()
        d.homing()  # E_CMD_PENDING then E_SUCCESS
        assert d.measure()["position"] == pytest.approx(110.0)
        info = d.position_pd(42.5, -10.0)
        assert info["position"] == pytest.approx(42.5) and info["force"] == pytest.approx(1.5)
        cmd, payload = srv.received[-1]
        assert cmd == 0xB1 and payload[0] == 0
        assert np.allclose(struct.unpack("<6f", payload[1:]), [42.5, -10.0, 15.0, 1e-3, 80.0, 80.0])
        assert srv.received[0] == (0x24, b"ack") and srv.received[1] == (0x20, b"\x01")
        with pytest.raises(DeployError, match=r"0x21 failed: E_RANGE_ERROR"):
            d.pre_position(150.0, 50.0)
        d.pre_position(30.0, 50.0)
        assert srv.position == pytest.approx(30.0)
        # a corrupted frame from us → the gripper answers E_CHECKSUM_ERROR (id 0, skipped) and keeps going
        frame = bytearray(encode_message(0xB0, b"\x00"))
        frame[-1] ^= 0xFF
        d.sock.sendall(bytes(frame))
        assert d.measure()["position"] == pytest.approx(30.0) and srv.bad_crc == 1
    finally:
        d.close()
    srv.thread.join(5)
    assert srv.ids()[-2:] == [0x22, 0x07]


def test_driver_errors_unknown_script_and_corrupt_reply():
    srv = FakeWSG(unknown_script=True)
    d = WSG50Driver("127.0.0.1", srv.port)
    d.connect()
    with pytest.raises(DeployError, match="E_CMD_UNKNOWN.*cmd_measure.lua"):
        d.measure()
    d.close()
    srv = FakeWSG(corrupt_replies=True)
    d = WSG50Driver("127.0.0.1", srv.port)
    d.connect()
    with pytest.raises(DeployError, match="CRC mismatch"):
        d.measure()
    d.close()
    srv.thread.join(5)
    with pytest.raises(DeployError, match="cannot connect"):
        WSG50Driver("127.0.0.1", srv.port, timeout_s=0.5).connect()  # server gone


def test_gripper_process_position_control_in_metres():
    srv = FakeWSG()
    g = WSG50Gripper(WSGConfig(gripper_ip="127.0.0.1", gripper_port=srv.port, max_speed=0.2), connect_timeout_s=60)
    g.start()
    try:
        assert g.get_states(1)["width"][-1] == pytest.approx(0.020)  # observe-only: measured, not homed
        assert set(srv.ids()) == {0xB0}  # reads only
        g.enable()
        assert g.get_states(1)["width"][-1] == pytest.approx(0.110)  # homed open
        g.schedule_waypoint(0.05, time.monotonic() + 0.1)
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and abs(g.get_states(1)["width"][-1] - 0.05) > 1e-4:
            g.check_ok()
            time.sleep(0.05)
        assert g.get_states(1)["width"][-1] == pytest.approx(0.05, abs=1e-4)
        sent = [struct.unpack("<6f", p[1:])[0] for c, p in srv.received if c == 0xB1]
        # the interpolator ramps (no jump to the target): monotone, with intermediate widths in mm
        assert np.all(np.diff(sent) <= 1e-4) and any(50.5 < w < 109.5 for w in sent)
    finally:
        g.stop()
    srv.thread.join(5)
    assert srv.ids()[-2:] == [0x22, 0x07]


def test_gripper_process_reports_connection_failure():
    g = WSG50Gripper(WSGConfig(gripper_ip="127.0.0.1", gripper_port=1), connect_timeout_s=60)
    with pytest.raises(SafetyStop, match="gripper WSG-50 127.0.0.1:1 stopped: WSG-50 at 127.0.0.1:1: cannot connect"):
        g.start()
    g.stop()
