"""Run a policy on a real UR arm (ur-rtde) with a WSG-50 and a UVC camera, or on the simulated UR5e — a Hydra app.

    python eval/deploy_ur.py robot=ur5e checkpoint=PATH out_dir=deploy_runs/try1  # asks before the arm moves
    python eval/deploy_ur.py robot=ur5e policy=reach out_dir=deploy_runs/reach   # scripted reach, no checkpoint
    python eval/deploy_ur.py robot=ur5e checkpoint=PATH dry_run=true            # nothing is sent to the robot
    python eval/deploy_ur.py robot=ur5e checkpoint=PATH confirm=true            # scripted: no prompt
    python eval/deploy_ur.py policy=reach out_dir=deploy_runs/sim              # the default robot: sim_ur5e
    python eval/deploy_ur.py robot=sim_ur5e checkpoint=PATH out_dir=deploy_runs/sim_ckpt
    python eval/deploy_ur.py --cfg job                                          # print the composed config

Writes ``out_dir/{episode.zarr.zip, episode.mp4, tcp_commanded_vs_reached.png, timing.json, deploy_ur.log}``.
A real arm (``robot.backend=rtde``) moves only after the operator types ``yes`` at the prompt that shows what
will move (robot IP, TCP, box, speed limits, current TCP, first target), or with ``confirm=true``.
Ctrl-C stops the robot. A safety stop prints one message and exits with status 3; a bad config or a refused
confirmation exits with status 2. See ``eval/README.md``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

CONFIG_DIR = str(Path(__file__).resolve().parent.parent / "configs")


@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="deploy_ur")
def main(cfg: DictConfig) -> None:
    from umi_aug.deploy.app import run_deploy
    from umi_aug.deploy.safety import SafetyStop
    from umi_aug.errors import UmiAugError
    from umi_aug.runtime import configure_threads, log_to_file

    from umi_aug.errors import DeployError
    from umi_aug.runtime import make_out_dir

    c = OmegaConf.to_container(cfg, resolve=True)
    out_dir = Path(c.get("out_dir") or "deploy_runs/latest")
    c["out_dir"] = str(out_dir)
    try:
        make_out_dir(out_dir, "out_dir", DeployError)
    except DeployError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
    log_to_file(out_dir / "deploy_ur.log")
    configure_threads(1)
    try:
        s = run_deploy(c, ask=_ask_on_terminal)
    except SafetyStop as exc:
        print(f"safety stop (robot halted): {exc}", file=sys.stderr)
        sys.exit(3)
    except UmiAugError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
    lat, per = s.get("obs_to_action_latency", {}), s.get("control_period", {})
    print(f"{s['cycles']} cycles, stop: {s['stop_reason']}; obs→action latency p50 {lat.get('p50_ms', float('nan')):.1f}"
          f" ms p99 {lat.get('p99_ms', float('nan')):.1f} ms; control period p50 {per.get('p50_ms', float('nan')):.2f}"
          f" ms p99 {per.get('p99_ms', float('nan')):.2f} ms" +
          (f"; final error {1000 * s['final_error_m']:.1f} mm" if "final_error_m" in s else "") + f"; {out_dir}")
    if s.get("dry_run"):
        w = s.get("dry_run_would_stop", {})
        print(f"dry run: nothing was sent; {w.get('n_commands', 0)} would-be command(s) would have stopped the run"
              + (f" (first in cycle {w['first_cycle']}: {w['reasons'][0]})" if w.get("n_commands") else ""))


def _ask_on_terminal(text: str) -> str | None:
    """Show ``text`` and read the operator's answer; None when stdin is not a terminal (scripted use needs
    ``confirm=true``)."""
    if not sys.stdin.isatty():
        return None
    print(text, file=sys.stderr)
    try:
        return input("Type yes to move the arm: ")
    except EOFError:
        return None


def _policy_override(argv: list[str]) -> list[str]:
    """``policy=NAME`` → ``deploy_policy=NAME`` (``configs/policy/`` is the training network group)."""
    return ["deploy_policy=" + a[len("policy="):] if a.startswith("policy=") else a for a in argv]


if __name__ == "__main__":
    sys.argv[1:] = _policy_override(sys.argv[1:])
    main()
