import argparse

import pytest

from umi_aug.errors import ReconError
from umi_aug.recon.cli import add_reconstruct_parser


def _parser():
    p = argparse.ArgumentParser()
    add_reconstruct_parser(p.add_subparsers(dest="cmd"))
    return p


def test_reconstruct_parser_defaults_and_bad_override(tmp_path):
    a = _parser().parse_args(["reconstruct", str(tmp_path), "--contact", "demo_a=12"])
    assert a.mode == "known_poses" and a.features == 2048 and a.contact == ["demo_a=12"]
    bad = _parser().parse_args(["reconstruct", str(tmp_path), "--contact", "demo_a"])
    with pytest.raises(ReconError, match="DEMO=FRAME"):
        bad.func(bad)
    missing = _parser().parse_args(["reconstruct", str(tmp_path / "nope")])
    with pytest.raises(ReconError, match="not a UMI session"):
        missing.func(missing)
