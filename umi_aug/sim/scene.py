"""The built-in tabletop scene, generated as MJCF in code (no downloads), with a seeded object layout.

World frame = UMI's table-tag frame: origin at the centre of the ArUco tag (id 13, 0.16 m, DICT_4X4_50) lying on
the table top, z up, table top at z = 0, the user stands at −y. Metres, radians.

Contents: a table with a high-frequency random-dot texture, textured floor / walls / ceiling (structure from
motion needs texture wherever the fisheye looks), a mug with a D-shaped handle (free joint, moved kinematically),
a pink plate, a few static distractors, and a UMI-like two-finger gripper on a mocap body whose frame IS the
fisheye camera's OpenCV frame (x right, y down, z forward), so the fingers appear at the bottom of every
eye-in-hand frame. Finger opening is set through two slide joints (:func:`set_gripper_width`).

The MJCF string references PNG textures by file name; their bytes are returned beside it
(``TabletopScene.assets``), so ``mujoco.MjModel.from_xml_string(xml, assets)`` compiles it directly and
:meth:`TabletopScene.write` puts both on disk.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from umi_aug.errors import SimError
from umi_aug.geometry import make_pose, matrix_to_quat_wxyz
from umi_aug.io_utils import atomic_write_bytes, atomic_write_text
from umi_aug.sim.camera_frames import CV_TO_MJ_CAMERA_AXES
from umi_aug.sim.gl import import_mujoco
from umi_aug.sim.textures import aruco_texture, encode_png, random_dot_texture

__all__ = [
    "MugSpec", "PlateSpec", "GripperSpec", "Distractor", "SceneLayout", "TabletopScene", "build_tabletop_scene",
    "mug_grasp_pose", "GRIPPER_BODY", "CAMERA_NAME", "MUG_BODY", "PLATE_BODY", "FINGER_JOINTS",
]

# ----------------------------------------------------------------------------------------------------- names
GRIPPER_BODY = "umi_gripper"  #: mocap body; its frame is the fisheye camera's OpenCV frame
CAMERA_NAME = "umi_fisheye_axis"  #: MuJoCo pinhole camera on the optical axis (MuJoCo axes), for convenience
MUG_BODY = "mug"
PLATE_BODY = "plate"
FINGER_JOINTS = ("finger_left_slide", "finger_right_slide")
GRIPPER_GEOM_PREFIX = "gripper_"

# ------------------------------------------------------------------------------------------------ room, table
TABLE_HALF = (0.60, 0.40)  #: table top half extents (x, y), m
TABLE_CENTER = (0.0, 0.20)  #: table top centre (x, y), m; the tag (origin) is 0.2 m from the near edge
TABLE_THICKNESS = 0.04
FLOOR_Z = -0.75
ROOM_X = (-1.6, 1.6)
ROOM_Y = (-1.2, 1.7)
CEILING_Z = 1.65
TAG_ID = 13
TAG_SIZE = 0.16  #: black square side, m (UMI table tag)
#: Objects are placed inside this table region (x range, y range), m.
OBJECT_REGION = ((-0.35, 0.35), (0.10, 0.50))
#: Near/far clip planes the scene is designed for (metres): fingers are >= 4 cm from the camera centre.
SCENE_NEAR = 0.005
SCENE_FAR = 12.0


@dataclass(frozen=True)
class MugSpec:
    """Mug geometry (mug frame: origin at the bottom centre, z up, handle towards +x). Metres."""

    radius: float = 0.040
    height: float = 0.095
    handle_radius: float = 0.030  #: radius of the D-shaped handle's centre line (in the mug's xz plane)
    handle_thickness: float = 0.011  #: capsule diameter of the handle
    handle_segments: int = 7
    rgba: tuple[float, float, float, float] = (0.16, 0.36, 0.78, 1.0)

    @property
    def handle_centre_x(self) -> float:
        """x of the handle arc's centre (slightly inside the wall so the arc meets it)."""
        return self.radius - 0.002

    @property
    def handle_outer_x(self) -> float:
        """x of the handle's outermost (vertical) bar centre line, the grasp point."""
        return self.handle_centre_x + self.handle_radius


@dataclass(frozen=True)
class PlateSpec:
    """Plate geometry (plate frame: origin at the bottom centre, z up). Metres."""

    radius: float = 0.10
    thickness: float = 0.012
    rim_radius: float = 0.005
    rim_segments: int = 20
    rgba: tuple[float, float, float, float] = (0.93, 0.52, 0.68, 1.0)

    @property
    def top_z(self) -> float:
        """Height of the plate's upper surface above its base, m."""
        return self.thickness


@dataclass(frozen=True)
class GripperSpec:
    """UMI-like gripper in the camera's OpenCV frame (x right, y down, z forward), metres.

    The fingers' inner faces are at ``x = ±width/2``; fingertips reach ``z = tip_z`` at the height of UMI's TCP
    (``y = 0.086``): the TCP (``[0, 0.086, 0.21965]``, umi_stack.md §1) sits between the fingertips.
    """

    max_width: float = 0.09
    tip_z: float = 0.226
    finger_base_z: float = 0.07
    finger_y: tuple[float, float] = (0.074, 0.098)
    finger_base_depth: float = 0.034  #: x extent of the fin-ray wedge at its base
    carriage_z: tuple[float, float] = (0.012, 0.07)  #: z extent of the finger carriages (on the rail)
    body_rgba: tuple[float, float, float, float] = (0.12, 0.12, 0.13, 1.0)
    finger_rgba: tuple[float, float, float, float] = (0.30, 0.33, 0.38, 1.0)


@dataclass(frozen=True)
class Distractor:
    """A static distractor object: MuJoCo geom type, size (MJCF ``size``) and world pose (4×4)."""

    name: str
    geom_type: str
    size: tuple[float, ...]
    T_world_obj: np.ndarray
    rgba: tuple[float, float, float, float]
    footprint_radius: float


@dataclass
class SceneLayout:
    """The seeded layout and the task-relevant poses of one scene (world = table-tag frame, metres).

    Attributes:
        seed: layout seed.
        T_world_mug: [4, 4] initial mug pose (bottom centre, handle along the mug's +x).
        T_world_plate: [4, 4] plate pose (bottom centre).
        T_world_tag: [4, 4] ArUco tag pose (identity: the world frame).
        T_mug_grasp: [4, 4] TCP pose in the mug frame when grasping the handle (OpenCV/TCP axes).
        T_world_grasp: [4, 4] ``T_world_mug @ T_mug_grasp``.
        T_world_mug_place: [4, 4] target mug pose: upright on the plate, handle pointing left (−x).
        grasp_pitch: downward tilt of the TCP z axis at grasp, radians.
        distractors: static objects.
    """

    seed: int
    T_world_mug: np.ndarray
    T_world_plate: np.ndarray
    T_world_tag: np.ndarray
    T_mug_grasp: np.ndarray
    T_world_grasp: np.ndarray
    T_world_mug_place: np.ndarray
    grasp_pitch: float
    mug: MugSpec = field(default_factory=MugSpec)
    plate: PlateSpec = field(default_factory=PlateSpec)
    gripper: GripperSpec = field(default_factory=GripperSpec)
    distractors: list[Distractor] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON description (poses as nested lists)."""

        def mat(a: np.ndarray) -> list:
            return np.asarray(a, dtype=np.float64).round(12).tolist()

        return {
            "frame": "world = UMI table-tag frame (tag id 13 at the origin), z up, metres",
            "seed": self.seed,
            "T_world_mug": mat(self.T_world_mug),
            "T_world_plate": mat(self.T_world_plate),
            "T_world_tag": mat(self.T_world_tag),
            "T_mug_grasp": mat(self.T_mug_grasp),
            "T_world_grasp": mat(self.T_world_grasp),
            "T_world_mug_place": mat(self.T_world_mug_place),
            "grasp_pitch_deg": math.degrees(self.grasp_pitch),
            "mug": asdict(self.mug),
            "plate": asdict(self.plate),
            "gripper": asdict(self.gripper),
            "tag": {"id": TAG_ID, "size_m": TAG_SIZE, "dictionary": "DICT_4X4_50"},
            "distractors": [
                {"name": d.name, "geom_type": d.geom_type, "size": list(d.size), "T_world_obj": mat(d.T_world_obj),
                 "rgba": list(d.rgba)}
                for d in self.distractors
            ],
        }


@dataclass
class TabletopScene:
    """MJCF text + texture bytes + layout of one built-in scene.

    Attributes:
        xml: MJCF string (textures referenced by file name).
        assets: {file name: PNG bytes}.
        layout: :class:`SceneLayout`.
    """

    xml: str
    assets: dict[str, bytes]
    layout: SceneLayout

    def compile(self):
        """Compile to a ``mujoco.MjModel`` (chooses the GL backend first, see :mod:`umi_aug.sim.gl`)."""
        mujoco = import_mujoco()
        try:
            return mujoco.MjModel.from_xml_string(self.xml, self.assets)
        except ValueError as exc:
            raise SimError(f"built-in tabletop MJCF failed to compile: {exc}") from exc

    def write(self, out_dir: str | Path) -> Path:
        """Write ``scene.xml`` and its textures into ``out_dir`` (atomic per file); returns the xml path.
        ``mujoco.MjModel.from_xml_path(out_dir/'scene.xml')`` loads it."""
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        for name, data in sorted(self.assets.items()):
            atomic_write_bytes(out / name, data)
        return atomic_write_text(out / "scene.xml", self.xml)


# ------------------------------------------------------------------------------------------------ helpers
def _f(x: float) -> str:
    """Fixed float formatting for a reproducible MJCF string."""
    s = f"{float(x):.6f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def _v(v) -> str:
    return " ".join(_f(x) for x in np.asarray(v, dtype=np.float64).reshape(-1))


def _rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _quat(R: np.ndarray) -> str:
    return _v(matrix_to_quat_wxyz(np.asarray(R, dtype=np.float64)))


def mug_grasp_pose(mug: MugSpec, pitch: float, depth: float = 0.004) -> np.ndarray:
    """TCP pose ``T_mug_tcp`` that pinches the handle's outer bar (mug frame, OpenCV/TCP axes).

    The TCP z axis (finger direction) points from outside the handle towards the mug axis, tilted down by
    ``pitch``; x (finger closing direction) is the mug's +y, perpendicular to the handle's plane, so the fingers
    straddle the bar; y (image down) has a downward component.

    Args:
        mug: mug geometry.
        pitch: tilt of the finger direction below horizontal, radians (0 = horizontal, pi/2 = straight down).
        depth: how far past the bar's centre line the TCP sits along the finger direction, metres.

    Returns:
        T_mug_tcp: np.ndarray,  # [4, 4]
    """
    z = np.array([-math.cos(pitch), 0.0, -math.sin(pitch)])
    x = np.array([0.0, 1.0, 0.0])
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=1)
    p = np.array([mug.handle_outer_x, 0.0, 0.5 * mug.height]) + depth * z
    return make_pose(R, p)


def _texture_assets(rng: np.random.Generator) -> dict[str, bytes]:
    tex = {
        "table.png": random_dot_texture(rng, 1024, (168, 128, 92), n_dots=3000, n_strokes=200),
        "floor.png": random_dot_texture(rng, 512, (95, 95, 100), n_dots=900, n_strokes=80),
        "wall_a.png": random_dot_texture(rng, 512, (190, 185, 170), n_dots=1000, n_strokes=80),
        "wall_b.png": random_dot_texture(rng, 512, (150, 170, 185), n_dots=1000, n_strokes=80),
        "ceiling.png": random_dot_texture(rng, 256, (215, 215, 210), n_dots=250, n_strokes=20, contrast=0.6),
        "distractor.png": random_dot_texture(rng, 256, (120, 160, 110), n_dots=300, n_strokes=30),
        "tag13.png": aruco_texture(TAG_ID, 240),
    }
    return {k: encode_png(v) for k, v in tex.items()}


def _sample_layout(rng: np.random.Generator, mug: MugSpec, plate: PlateSpec, n_distractors: int):
    (x0, x1), (y0, y1) = OBJECT_REGION
    mug_fp = mug.handle_outer_x + 0.01
    for _ in range(1000):
        mug_xy = np.array([rng.uniform(x0 + mug_fp, -0.02), rng.uniform(y0 + 0.05, y1 - mug_fp)])
        plate_xy = np.array([rng.uniform(0.05, x1 - plate.radius + 0.05), rng.uniform(y0 + 0.03, y1 - 0.05)])
        if np.linalg.norm(mug_xy - plate_xy) >= mug_fp + plate.radius + 0.08:
            break
    else:  # pragma: no cover - the ranges always admit a layout
        raise SimError("could not place the mug and plate without overlap")
    mug_yaw = math.pi + rng.uniform(-math.radians(50.0), math.radians(50.0))
    handle_dir = np.array([math.cos(mug_yaw), math.sin(mug_yaw)])

    def seg_dist(p, a, b):
        ab = b - a
        t = np.clip(np.dot(p - a, ab) / max(np.dot(ab, ab), 1e-12), 0.0, 1.0)
        return float(np.linalg.norm(p - (a + t * ab)))

    kinds = ("box", "cylinder", "sphere", "box", "cylinder", "ellipsoid")
    palette = [(0.85, 0.75, 0.15, 1.0), (0.20, 0.65, 0.35, 1.0), (0.75, 0.25, 0.20, 1.0),
               (0.55, 0.40, 0.75, 1.0), (0.95, 0.55, 0.15, 1.0), (0.30, 0.70, 0.80, 1.0)]
    distractors: list[Distractor] = []
    placed = [(mug_xy, mug_fp), (plate_xy, plate.radius)]
    approach = mug_xy + handle_dir * 0.25
    for i in range(n_distractors):
        kind = kinds[i % len(kinds)]
        for _ in range(500):
            if kind == "box":
                size = (rng.uniform(0.02, 0.04), rng.uniform(0.02, 0.04), rng.uniform(0.02, 0.05))
                fp = math.hypot(size[0], size[1])
                z = size[2]
            elif kind == "cylinder":
                size = (rng.uniform(0.02, 0.035), rng.uniform(0.025, 0.06))
                fp, z = size[0], size[1]
            elif kind == "sphere":
                size = (rng.uniform(0.025, 0.04),)
                fp, z = size[0], size[0]
            else:
                size = (rng.uniform(0.03, 0.05), rng.uniform(0.02, 0.035), rng.uniform(0.015, 0.03))
                fp, z = max(size[0], size[1]), size[2]
            xy = np.array([rng.uniform(x0 + fp, x1 - fp), rng.uniform(y0 + fp, y1 + 0.05 - fp)])
            ok = all(np.linalg.norm(xy - c) >= r + fp + 0.03 for c, r in placed)
            ok = ok and seg_dist(xy, mug_xy, plate_xy) >= fp + 0.09  # keep the transport corridor free
            ok = ok and seg_dist(xy, mug_xy, approach) >= fp + 0.09  # and the approach to the handle
            if ok:
                break
        else:
            continue  # no room: fewer distractors
        yaw = rng.uniform(-math.pi, math.pi)
        T = make_pose(_rot_z(yaw), np.array([xy[0], xy[1], z]))
        distractors.append(Distractor(f"distractor_{i}", kind, tuple(float(s) for s in size), T,
                                      palette[i % len(palette)], float(fp)))
        placed.append((xy, fp))
    return mug_xy, mug_yaw, plate_xy, distractors


# ----------------------------------------------------------------------------------------------- the MJCF
def _gripper_xml(g: GripperSpec) -> str:
    """Gripper geoms in the mocap body's frame (= OpenCV camera frame)."""
    ya, yb = g.finger_y
    L = g.tip_z - g.finger_base_z
    lines = []
    # housing below/behind the fingers (visible at the bottom edge of the image), rail, camera mount
    lines.append(f'<geom name="{GRIPPER_GEOM_PREFIX}housing" type="box" pos="0 0.112 0.0" '
                 f'size="0.07 0.012 0.025" material="gripper_body"/>')
    lines.append(f'<geom name="{GRIPPER_GEOM_PREFIX}rail" type="box" pos="0 0.104 0.03" '
                 f'size="0.1 0.006 0.016" material="gripper_body"/>')
    lines.append(f'<geom name="{GRIPPER_GEOM_PREFIX}mount" type="box" pos="0 0.03 -0.03" '
                 f'size="0.03 0.02 0.02" material="gripper_body"/>')
    for side, sgn, joint in (("left", -1.0, FINGER_JOINTS[0]), ("right", 1.0, FINGER_JOINTS[1])):
        # finger body origin on the closing axis (x = 0); the slide joint moves it to x = ±width/2
        cz0, cz1 = g.carriage_z
        carriage_c = (sgn * 0.021, 0.5 * (ya + yb) + 0.004, 0.5 * (cz0 + cz1))
        carriage_s = (0.017, 0.5 * (yb - ya) + 0.002, 0.5 * (cz1 - cz0))
        lines.append(f'<body name="finger_{side}" pos="0 0 0">')
        lines.append(f'  <joint name="{joint}" type="slide" axis="1 0 0" range="{_f(-g.max_width)} '
                     f'{_f(g.max_width)}" limited="false"/>')
        lines.append(f'  <geom name="{GRIPPER_GEOM_PREFIX}carriage_{side}" type="box" pos="{_v(carriage_c)}" '
                     f'size="{_v(carriage_s)}" material="gripper_body"/>')
        lines.append(f'  <geom name="{GRIPPER_GEOM_PREFIX}finger_{side}" type="mesh" mesh="finger_{side}" '
                     f'material="gripper_finger"/>')
        # a light contact pad on the inner face (visual cue of the opening)
        pad_c = (sgn * 0.0015, 0.5 * (ya + yb), g.finger_base_z + 0.55 * L)
        pad_s = (0.0015, 0.5 * (yb - ya) * 0.9, 0.4 * L)
        lines.append(f'  <geom name="{GRIPPER_GEOM_PREFIX}pad_{side}" type="box" pos="{_v(pad_c)}" '
                     f'size="{_v(pad_s)}" rgba="0.85 0.85 0.8 1"/>')
        lines.append("</body>")
    return "\n        ".join(lines)


def _finger_mesh_vertices(g: GripperSpec, sgn: float) -> np.ndarray:
    """Fin-ray wedge (8 vertices): flat inner face at x = 0, outer face tapering to the tip. Finger frame."""
    ya, yb = g.finger_y
    out = sgn * g.finger_base_depth
    tip_out = sgn * 0.004
    pts = []
    for y in (ya, yb):
        pts += [(0.0, y, g.finger_base_z), (out, y, g.finger_base_z), (0.0, y, g.tip_z), (tip_out, y, g.tip_z)]
    return np.array(pts)


def build_tabletop_scene(
    seed: int = 0,
    n_distractors: int = 4,
    mug: MugSpec | None = None,
    plate: PlateSpec | None = None,
    gripper: GripperSpec | None = None,
    grasp_pitch_deg: float = 50.0,
) -> TabletopScene:
    """Generate the built-in tabletop scene.

    Args:
        seed: layout and texture seed (same seed → identical xml and asset bytes).
        n_distractors: number of static distractor objects (fewer if the table runs out of room).
        mug, plate, gripper: geometry overrides.
        grasp_pitch_deg: downward tilt of the fingers when grasping the handle, degrees.

    Returns:
        :class:`TabletopScene`.
    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise SimError(f"build_tabletop_scene: seed must be a non-negative int, got {seed!r}")
    mug = mug or MugSpec()
    plate = plate or PlateSpec()
    gripper = gripper or GripperSpec()
    ss = np.random.SeedSequence([int(seed), 0x5CE4E])
    rng_layout, rng_tex = (np.random.default_rng(s) for s in ss.spawn(2))
    mug_xy, mug_yaw, plate_xy, distractors = _sample_layout(rng_layout, mug, plate, int(n_distractors))
    assets = _texture_assets(rng_tex)

    T_world_mug = make_pose(_rot_z(mug_yaw), np.array([mug_xy[0], mug_xy[1], 0.0]))
    T_world_plate = make_pose(np.eye(3), np.array([plate_xy[0], plate_xy[1], 0.0]))
    pitch = math.radians(float(grasp_pitch_deg))
    T_mug_grasp = mug_grasp_pose(mug, pitch)
    T_world_mug_place = make_pose(_rot_z(math.pi), np.array([plate_xy[0], plate_xy[1], plate.top_z]))
    layout = SceneLayout(
        seed=int(seed), T_world_mug=T_world_mug, T_world_plate=T_world_plate, T_world_tag=np.eye(4),
        T_mug_grasp=T_mug_grasp, T_world_grasp=T_world_mug @ T_mug_grasp, T_world_mug_place=T_world_mug_place,
        grasp_pitch=pitch, mug=mug, plate=plate, gripper=gripper, distractors=distractors,
    )
    xml = _mjcf(layout)
    return TabletopScene(xml=xml, assets=assets, layout=layout)


def _mjcf(L: SceneLayout) -> str:
    mug, plate, g = L.mug, L.plate, L.gripper
    tcx, tcy = TABLE_CENTER
    thx, thy = TABLE_HALF
    room_cx, room_cy = 0.5 * (ROOM_X[0] + ROOM_X[1]), 0.5 * (ROOM_Y[0] + ROOM_Y[1])
    room_hx, room_hy = 0.5 * (ROOM_X[1] - ROOM_X[0]), 0.5 * (ROOM_Y[1] - ROOM_Y[0])
    wall_hz = 0.5 * (CEILING_Z - FLOOR_Z)
    wall_cz = 0.5 * (CEILING_Z + FLOOR_Z)
    tag_half = 0.5 * TAG_SIZE * (1.0 + 2.0 / 6.0)

    legs = []
    for i, (sx, sy) in enumerate(((-1, -1), (1, -1), (-1, 1), (1, 1))):
        lx, ly = tcx + sx * (thx - 0.05), tcy + sy * (thy - 0.05)
        lz = 0.5 * (FLOOR_Z - TABLE_THICKNESS)
        legs.append(f'<geom name="table_leg_{i}" type="box" pos="{_v((lx, ly, lz))}" '
                    f'size="{_v((0.025, 0.025, 0.5 * (-TABLE_THICKNESS - FLOOR_Z)))}" material="metal"/>')

    # mug: body + dark interior disc + bottom + D handle (capsules on an arc in the mug's xz plane)
    mug_geoms = [
        f'<geom name="mug_body" type="cylinder" pos="0 0 {_f(mug.height / 2)}" '
        f'size="{_f(mug.radius)} {_f(mug.height / 2)}" material="mug"/>',
        f'<geom name="mug_inside" type="cylinder" pos="0 0 {_f(mug.height + 0.0004)}" '
        f'size="{_f(mug.radius - 0.005)} 0.0004" rgba="0.10 0.07 0.05 1" contype="0" conaffinity="0"/>',
    ]
    n = mug.handle_segments
    angs = np.linspace(-math.radians(80), math.radians(80), n + 1)
    cx, cz, r = mug.handle_centre_x, 0.5 * mug.height, mug.handle_radius
    for i in range(n):
        p0 = (cx + r * math.cos(angs[i]), 0.0, cz + r * math.sin(angs[i]))
        p1 = (cx + r * math.cos(angs[i + 1]), 0.0, cz + r * math.sin(angs[i + 1]))
        mug_geoms.append(f'<geom name="mug_handle_{i}" type="capsule" fromto="{_v(p0 + p1)}" '
                         f'size="{_f(mug.handle_thickness / 2)}" material="mug"/>')

    plate_geoms = [f'<geom name="plate_base" type="cylinder" pos="0 0 {_f(plate.thickness / 2)}" '
                   f'size="{_f(plate.radius)} {_f(plate.thickness / 2)}" material="plate"/>']
    m = plate.rim_segments
    rr = plate.radius - plate.rim_radius
    for i in range(m):
        a0, a1 = 2 * math.pi * i / m, 2 * math.pi * (i + 1) / m
        p0 = (rr * math.cos(a0), rr * math.sin(a0), plate.thickness)
        p1 = (rr * math.cos(a1), rr * math.sin(a1), plate.thickness)
        plate_geoms.append(f'<geom name="plate_rim_{i}" type="capsule" fromto="{_v(p0 + p1)}" '
                           f'size="{_f(plate.rim_radius)}" material="plate"/>')

    dist_xml = []
    for k, d in enumerate(L.distractors):
        mat = "distractor_tex" if k % 2 == 0 else None
        rgba = "" if mat else f' rgba="{_v(d.rgba)}"'
        matattr = f' material="{mat}"' if mat else ""
        dist_xml.append(
            f'<body name="{d.name}" pos="{_v(d.T_world_obj[:3, 3])}" quat="{_quat(d.T_world_obj[:3, :3])}">'
            f'<geom name="{d.name}_geom" type="{d.geom_type}" size="{_v(d.size)}"{matattr}{rgba}/></body>'
        )

    fl = _finger_mesh_vertices(g, -1.0)
    fr = _finger_mesh_vertices(g, 1.0)
    mug_q = _quat(L.T_world_mug[:3, :3])
    mug_p = _v(L.T_world_mug[:3, 3])
    cam_quat = _quat(CV_TO_MJ_CAMERA_AXES)  # MuJoCo camera axes in the (OpenCV) body frame
    return f"""<mujoco model="umi_aug_tabletop_seed{L.seed}">
  <compiler angle="radian" autolimits="true"/>
  <option gravity="0 0 -9.81" timestep="0.002"/>
  <statistic center="0 0.2 0.1" extent="2.0"/>
  <visual>
    <headlight active="1" ambient="0.32 0.32 0.32" diffuse="0 0 0" specular="0 0 0"/>
    <map znear="{_f(SCENE_NEAR / 2.0)}" zfar="{_f(SCENE_FAR / 2.0)}"/>
    <quality shadowsize="2048" offsamples="0"/>
    <global offwidth="1024" offheight="1024"/>
  </visual>
  <asset>
    <texture name="tex_table" type="2d" file="table.png"/>
    <texture name="tex_floor" type="2d" file="floor.png"/>
    <texture name="tex_wall_a" type="2d" file="wall_a.png"/>
    <texture name="tex_wall_b" type="2d" file="wall_b.png"/>
    <texture name="tex_ceiling" type="2d" file="ceiling.png"/>
    <texture name="tex_distractor" type="2d" file="distractor.png"/>
    <texture name="tex_tag" type="2d" file="tag13.png"/>
    <material name="table" texture="tex_table" texrepeat="2 2" texuniform="true" specular="0.15" shininess="0.2"/>
    <material name="floor" texture="tex_floor" texrepeat="1 1" texuniform="true" specular="0.05"/>
    <material name="wall_a" texture="tex_wall_a" texrepeat="0.8 0.8" texuniform="true" specular="0.02"/>
    <material name="wall_b" texture="tex_wall_b" texrepeat="0.8 0.8" texuniform="true" specular="0.02"/>
    <material name="ceiling" texture="tex_ceiling" texrepeat="0.6 0.6" texuniform="true" specular="0"/>
    <material name="distractor_tex" texture="tex_distractor" texrepeat="8 8" texuniform="true" specular="0.1"/>
    <material name="tag" texture="tex_tag" texrepeat="1 1" specular="0.05"/>
    <material name="metal" rgba="0.35 0.35 0.38 1" specular="0.4" shininess="0.5"/>
    <material name="mug" rgba="{_v(mug.rgba)}" specular="0.35" shininess="0.6"/>
    <material name="plate" rgba="{_v(plate.rgba)}" specular="0.25" shininess="0.4"/>
    <material name="gripper_body" rgba="{_v(g.body_rgba)}" specular="0.2"/>
    <material name="gripper_finger" rgba="{_v(g.finger_rgba)}" specular="0.1"/>
    <mesh name="finger_left" vertex="{_v(fl)}"/>
    <mesh name="finger_right" vertex="{_v(fr)}"/>
  </asset>
  <worldbody>
    <light name="key" directional="true" pos="0 0 3" dir="-0.3 0.35 -1" diffuse="0.5 0.5 0.5" specular="0.15 0.15 0.15"/>
    <light name="fill" pos="0.9 -0.9 1.3" dir="-0.5 0.6 -0.7" diffuse="0.28 0.28 0.3" specular="0.05 0.05 0.05"/>
    <light name="back" pos="-0.8 1.2 1.4" dir="0.4 -0.6 -0.7" diffuse="0.18 0.18 0.16" specular="0 0 0"/>
    <geom name="floor" type="plane" pos="{_v((room_cx, room_cy, FLOOR_Z))}" size="{_v((room_hx, room_hy, 0.1))}" material="floor"/>
    <geom name="ceiling" type="plane" pos="{_v((room_cx, room_cy, CEILING_Z))}" quat="0 1 0 0" size="{_v((room_hx, room_hy, 0.1))}" material="ceiling"/>
    <geom name="wall_far" type="plane" pos="{_v((room_cx, ROOM_Y[1], wall_cz))}" quat="{_quat(_rot_x(math.pi / 2))}" size="{_v((room_hx, wall_hz, 0.1))}" material="wall_a"/>
    <geom name="wall_near" type="plane" pos="{_v((room_cx, ROOM_Y[0], wall_cz))}" quat="{_quat(_rot_x(-math.pi / 2))}" size="{_v((room_hx, wall_hz, 0.1))}" material="wall_b"/>
    <geom name="wall_left" type="plane" pos="{_v((ROOM_X[0], room_cy, wall_cz))}" quat="{_quat(_rot_y(math.pi / 2))}" size="{_v((wall_hz, room_hy, 0.1))}" material="wall_b"/>
    <geom name="wall_right" type="plane" pos="{_v((ROOM_X[1], room_cy, wall_cz))}" quat="{_quat(_rot_y(-math.pi / 2))}" size="{_v((wall_hz, room_hy, 0.1))}" material="wall_a"/>
    <geom name="table_top" type="box" pos="{_v((tcx, tcy, -TABLE_THICKNESS / 2))}" size="{_v((thx, thy, TABLE_THICKNESS / 2))}" material="table"/>
    {chr(10).join('    ' + s for s in legs).strip()}
    <geom name="tag_{TAG_ID}" type="box" pos="0 0 0.0004" size="{_f(tag_half)} {_f(tag_half)} 0.0004" material="tag" contype="0" conaffinity="0"/>
    <body name="{MUG_BODY}" pos="{mug_p}" quat="{mug_q}">
      <freejoint name="mug_free"/>
      {chr(10).join('      ' + s for s in mug_geoms).strip()}
    </body>
    <body name="{PLATE_BODY}" pos="{_v(L.T_world_plate[:3, 3])}">
      {chr(10).join('      ' + s for s in plate_geoms).strip()}
    </body>
    {chr(10).join('    ' + s for s in dist_xml).strip()}
    <body name="{GRIPPER_BODY}" mocap="true" pos="0 0 0.5" quat="0 1 0 0">
      <camera name="{CAMERA_NAME}" pos="0 0 0" quat="{cam_quat}" fovy="90"/>
        {_gripper_xml(g)}
    </body>
  </worldbody>
</mujoco>
"""
