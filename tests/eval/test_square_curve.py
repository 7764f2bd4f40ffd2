"""eval/square_curve.py's bookkeeping: training minutes of a run resumed across processes, and its records."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _module():
    spec = importlib.util.spec_from_file_location("square_curve", ROOT / "eval" / "square_curve.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_training_minutes_sum_the_processes_of_a_resumed_run(tmp_path):
    mod = _module()
    rows = [{"step": s, "train_loss": 1.0, "time": 6.0 * s} for s in range(1, 11)]  # first process: 60 s
    rows += [{"epoch": 0, "step": 10, "train_loss_epoch": 1.0}]  # an epoch row has no time
    rows += [{"step": s, "train_loss": 1.0, "time": 3.0 * (s - 10)} for s in range(11, 21)]  # resumed: 30 s
    (tmp_path / "logs.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    assert abs(mod._train_minutes(tmp_path) - 1.5) < 1e-9
    rec = tmp_path / "r.jsonl"
    assert mod._rows(rec) == []
    rec.write_text(json.dumps({"step": 3000}) + "\n\n" + json.dumps({"step": 6000}) + "\n")
    assert [r["step"] for r in mod._rows(rec)] == [3000, 6000]


def test_bad_arguments_are_refused(capsys):
    mod = _module()
    import pytest

    with pytest.raises(SystemExit):
        mod.main(["--every", "0", "--name", "x"])
    assert "--every" in capsys.readouterr().err
    assert mod.main(["--name", "x", "--demos", "/nonexistent/demos"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "/nonexistent/demos" in err and "Traceback" not in err


def test_a_second_run_and_another_recipe_are_refused(tmp_path, capsys):
    """Two processes on one curve name, or a continuation with other training overrides, would mix or clobber the
    record: each is refused with one error line before anything trains."""
    from umi_aug.io_utils import exclusive_run_lock

    mod = _module()
    common = ["--name", "c", "--out", str(tmp_path / "out"), "--record", str(tmp_path / "rec"),
              "--demos", str(tmp_path / "no_demos")]
    with exclusive_run_lock(tmp_path / "out" / "c" / "curve.lock", "test holder"):
        assert mod.main(common) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "curve.lock" in err and "another" in err and "Traceback" not in err

    (tmp_path / "rec").mkdir()
    row = {"name": "c", "step": 3000, "train_overrides": ["policy=small"]}
    (tmp_path / "rec" / "c.jsonl").write_text(json.dumps(row) + "\n")
    assert mod.main([*common, "--", "policy=small_regression"]) == 2
    err = capsys.readouterr().err
    assert "c.jsonl" in err and "policy=small_regression" in err and "another --name" in err
    assert mod.main([*common, "--", "policy=small"]) == 2  # the same recipe gets past, to the demo check
    assert "no_demos" in capsys.readouterr().err


def test_another_schedule_length_is_refused(tmp_path, capsys):
    """Resuming a curve with another --max-steps would re-stretch its cosine schedule mid-run (the learning rate
    rises again): refused from the record's rows and from the run's own checkpoint, before anything trains."""
    from umi_aug.policy.checkpoint import save_checkpoint

    mod = _module()
    common = ["--name", "c", "--every", "3000", "--out", str(tmp_path / "out"), "--record", str(tmp_path / "rec"),
              "--demos", str(tmp_path / "no_demos"), "--", "policy=small"]
    (tmp_path / "rec").mkdir()
    row = {"name": "c", "step": 3000, "train_overrides": ["policy=small"], "max_steps": 18000}
    (tmp_path / "rec" / "c.jsonl").write_text(json.dumps(row) + "\n")
    assert mod.main(["--max-steps", "27000", *common]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "c.jsonl" in err and "18000" in err and "27000" in err
    assert mod.main(["--max-steps", "18000", *common]) == 2  # the same schedule gets past, to the demo check
    assert "no_demos" in capsys.readouterr().err

    # an older record without max_steps: the run's checkpoint still knows its schedule
    older = {k: v for k, v in row.items() if k != "max_steps"}
    (tmp_path / "rec" / "c.jsonl").write_text(json.dumps(older) + "\n")
    latest = tmp_path / "out" / "c" / "run" / "checkpoints" / "latest.ckpt"
    latest.parent.mkdir(parents=True)
    save_checkpoint(latest, {"cfg": {"training": {"max_steps": 18000}}, "state_dicts": {}, "pickles": {}})
    assert mod.main(["--max-steps", "27000", *common]) == 2
    err = capsys.readouterr().err
    assert "latest.ckpt" in err and "training.max_steps=18000" in err and "27000" in err
    assert mod.main(["--max-steps", "18000", *common]) == 2
    assert "no_demos" in capsys.readouterr().err


def test_dataset_files_of_a_training_buffer(tmp_path):
    """--dataset: an export's original episodes (meta/aug_id < 0) and all of its episodes; a bad file, one error."""
    import numpy as np
    import pytest

    from umi_aug.data.replay_buffer import ReplayBuffer
    from umi_aug.errors import AugmentError

    mod = _module()
    buf = ReplayBuffer.create()
    for _ in range(5):
        buf.add_episode({"camera0_rgb": np.zeros((3, 8, 8, 3), np.uint8),
                         "robot0_eef_pos": np.zeros((3, 3), np.float32)})
    buf.meta.create_dataset("aug_id", data=np.array([-1, -1, 0, 1, 2]))
    path = buf.save(tmp_path / "aug.zarr.zip")
    z, size, n_demos, n_episodes = mod._dataset_files(str(path))
    assert (z, size, n_demos, n_episodes) == (path.resolve(), 8, 2, 5)
    with pytest.raises(AugmentError, match="--dataset .*nope"):
        mod._dataset_files(str(tmp_path / "nope.zarr.zip"))
