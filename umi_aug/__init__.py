"""umi-aug: action-view augmentation for UMI / Diffusion Policy.

One eye-in-hand fisheye demonstration plus a short scan of the scene becomes thousands of new, physically
valid demonstrations (new start poses, new obstacles) with actions from trajectory optimisation and fisheye
images rendered from a 3D Gaussian Splatting model of the scene.

Stages (one sub-package each, data flows one way): ``geometry`` and ``camera`` → ``data`` → ``sim`` →
``recon`` → ``splat`` → ``traj`` → ``augment`` → ``policy`` → ``eval``. Importing this package does no work.
"""

__version__ = "0.1.0"
