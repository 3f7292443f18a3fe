"""The scene library: named, procedurally varied recipes for animated test and training scenes.

A recipe is a function `(rng, frames) -> AnimatedScene`. Everything here is plain data (NumPy arrays and
dicts); `model.data.render` turns it into Mitsuba scenes. Each recipe stresses something a denoiser must
survive: fine texture, glossy metal, glass, a moving light, disocclusion, fast motion, fireflies, a cut.
The seed varies colours, placements, textures and paths, so scenes held out of training are really unseen.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from model.data.camera import Camera
from model.data.transforms import compose, rotate, scale, translate


@dataclass(frozen=True)
class ImageTexture:
    """An RGB texture in [0, 1] (H, W, 3), repeated `tiles` times across the shape's uv square."""

    pixels: np.ndarray
    tiles: float = 1.0


Colour = tuple[float, float, float]
Reflectance = Colour | ImageTexture


@dataclass(frozen=True)
class Material:
    """A Mitsuba BSDF plus the values the guide buffers need but Mitsuba cannot report per pixel.

    `roughness` is the perceptual roughness (GGX alpha = roughness**2; 1 for diffuse). `specular_albedo`
    approximates the directional specular reflectance: the tint of a metal (its Fresnel term is 1 with
    Mitsuba's material 'none'), 0.04 for the coating of plastics (Fresnel at normal incidence, IOR 1.5) and 1
    for glass.
    """

    kind: str  # diffuse | plastic | metal | glass
    reflectance: Reflectance = (0.5, 0.5, 0.5)
    roughness: float = 1.0
    specular_albedo: Colour = (0.0, 0.0, 0.0)


def diffuse(reflectance: Reflectance) -> Material:
    return Material("diffuse", reflectance, 1.0, (0.0, 0.0, 0.0))


def plastic(reflectance: Reflectance, roughness: float) -> Material:
    return Material("plastic", reflectance, roughness, (0.04, 0.04, 0.04))


def metal(tint: Colour, roughness: float) -> Material:
    return Material("metal", tint, roughness, tint)


def glass(roughness: float = 0.0) -> Material:
    return Material("glass", (1.0, 1.0, 1.0), roughness, (1.0, 1.0, 1.0))


@dataclass
class SceneObject:
    """One shape: Mitsuba shape type ('sphere', 'cube', 'rectangle', 'cylinder', 'disk'), per-frame to_world.

    An object with `emission` is an area light; it may still move (its motion vectors are exact too).
    """

    name: str
    shape: str
    transforms: list[np.ndarray]
    material: Material = field(default_factory=lambda: diffuse((0.5, 0.5, 0.5)))
    emission: Colour | None = None


@dataclass
class AnimatedScene:
    """A scene over `frames` frames: one camera per frame, objects with per-frame transforms, a sky."""

    name: str
    cameras: list[Camera]
    objects: list[SceneObject]
    sky: Colour = (0.0, 0.0, 0.0)
    cuts: frozenset[int] = frozenset()

    @property
    def frames(self) -> int:
        return len(self.cameras)

    def validate(self) -> None:
        for obj in self.objects:
            if len(obj.transforms) != self.frames:
                raise ValueError(f"scene {self.name!r}: object {obj.name!r} has {len(obj.transforms)} "
                                 f"transforms for {self.frames} frames")


Recipe = Callable[[np.random.Generator, int], AnimatedScene]
SCENES: dict[str, Recipe] = {}
DESCRIPTIONS: dict[str, str] = {}


def recipe(name: str, description: str):
    def register(function: Recipe) -> Recipe:
        SCENES[name] = function
        DESCRIPTIONS[name] = description
        return function
    return register


def build_scene(name: str, seed: int, frames: int) -> AnimatedScene:
    if name not in SCENES:
        raise KeyError(f"unknown scene {name!r}; known scenes: {', '.join(sorted(SCENES))}")
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    scene = SCENES[name](np.random.default_rng(seed), frames)
    scene.validate()
    return scene


# ----------------------------------------------------------------------------------------------- helpers

def _static(matrix: np.ndarray, frames: int) -> list[np.ndarray]:
    return [matrix] * frames


def _progress(frames: int) -> np.ndarray:
    """Normalized time per frame in [0, 1] (0 for a one-frame sequence)."""
    return np.linspace(0.0, 1.0, frames) if frames > 1 else np.zeros(1)


def _colour(rng: np.random.Generator, low: float = 0.15, high: float = 0.85) -> Colour:
    return tuple(float(c) for c in rng.uniform(low, high, 3))


def _room(rng: np.random.Generator, frames: int, size: float = 4.0, floor: Reflectance | None = None,
          wall: Reflectance | None = None) -> list[SceneObject]:
    """An open box: floor, back wall and two side walls around the origin, floor at y = 0."""
    half = size / 2
    floor_material = diffuse(floor if floor is not None else _colour(rng, 0.3, 0.7))
    wall_material = diffuse(wall if wall is not None else _colour(rng, 0.3, 0.8))
    return [
        SceneObject("floor", "rectangle", _static(compose(rotate((1, 0, 0), -90), scale(3 * half)), frames),
                    floor_material),
        SceneObject("back_wall", "rectangle", _static(compose(translate(0, half, -half), scale(half)), frames),
                    wall_material),
        SceneObject("left_wall", "rectangle",
                    _static(compose(translate(-half, half, 0), rotate((0, 1, 0), 90), scale(half)), frames),
                    diffuse(_colour(rng, 0.3, 0.8))),
        SceneObject("right_wall", "rectangle",
                    _static(compose(translate(half, half, 0), rotate((0, 1, 0), -90), scale(half)), frames),
                    diffuse(_colour(rng, 0.3, 0.8))),
    ]


def _ceiling_light(frames: int, height: float = 3.9, size: float = 0.6, power: float = 12.0) -> SceneObject:
    return SceneObject("ceiling_light", "rectangle",
                       _static(compose(translate(0, height, 0), rotate((1, 0, 0), 90), scale(size)), frames),
                       diffuse((0.0, 0.0, 0.0)), emission=(power, power, power * 0.9))


def _orbit_cameras(rng: np.random.Generator, frames: int, degrees: float, radius: float = 6.0,
                   height: float = 2.0, target=(0.0, 0.8, 0.0), fov: float = 50.0) -> list[Camera]:
    start = rng.uniform(-20, 20)
    cameras = []
    for t in _progress(frames):
        angle = np.radians(start + degrees * (t - 0.5))
        origin = (radius * np.sin(angle), height, radius * np.cos(angle))
        cameras.append(Camera(origin, target, (0.0, 1.0, 0.0), fov))
    return cameras


def _sphere(name: str, centre, radius: float, material: Material, frames: int) -> SceneObject:
    return SceneObject(name, "sphere", _static(compose(translate(*centre), scale(radius)), frames), material)


def _box(name: str, centre, half_size, yaw: float, material: Material, frames: int) -> SceneObject:
    return SceneObject(name, "cube", _static(compose(translate(*centre), rotate((0, 1, 0), yaw),
                                                     scale(*half_size)), frames), material)


def _scattered_positions(rng: np.random.Generator, count: int, extent: float = 1.4) -> list[tuple[float, float]]:
    """`count` (x, z) floor positions at least 0.8 apart, so that objects do not intersect."""
    positions: list[tuple[float, float]] = []
    while len(positions) < count:
        candidate = tuple(float(v) for v in rng.uniform(-extent, extent, 2))
        if all(np.hypot(candidate[0] - p[0], candidate[1] - p[1]) > 0.8 for p in positions):
            positions.append(candidate)
    return positions


# ------------------------------------------------------------------------------------- procedural textures

def stripes_texture(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """Thin stripes at a random angle and period (2-5 texels): detail finer than a render pixel."""
    y, x = np.mgrid[0:size, 0:size].astype(np.float64)
    angle = rng.uniform(0, np.pi)
    period = rng.uniform(2.0, 5.0)
    phase = (x * np.cos(angle) + y * np.sin(angle)) / period
    mask = (np.sin(2 * np.pi * phase) > 0).astype(np.float64)[..., None]
    a, b = np.array(_colour(rng, 0.05, 0.35)), np.array(_colour(rng, 0.6, 0.95))
    return (a * (1 - mask) + b * mask).astype(np.float32)


def noise_texture(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """Multi-octave value noise: detail at every scale, from a few texels up."""
    image = np.zeros((size, size))
    for octave in range(1, 6):
        cells = 2 ** (octave + 1)
        grid = rng.uniform(0, 1, (cells + 1, cells + 1))
        coords = np.linspace(0, cells, size, endpoint=False)
        i = np.floor(coords).astype(int)
        f = coords - i
        rows = grid[i][:, i] * (1 - f)[None, :] + grid[i][:, i + 1] * f[None, :]
        rows_next = grid[i + 1][:, i] * (1 - f)[None, :] + grid[i + 1][:, i + 1] * f[None, :]
        image += (rows * (1 - f)[:, None] + rows_next * f[:, None]) / 2 ** (octave - 1)
    image = (image - image.min()) / (np.ptp(image) + 1e-9)
    a, b = np.array(_colour(rng, 0.05, 0.4)), np.array(_colour(rng, 0.5, 0.95))
    return (a + (b - a) * image[..., None]).astype(np.float32)


def bricks_texture(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """Bricks with thin mortar lines and per-brick colour variation."""
    rows, cols = int(rng.integers(12, 24)), int(rng.integers(6, 12))
    y, x = np.mgrid[0:size, 0:size] / size
    row = np.floor(y * rows)
    shifted = x * cols + 0.5 * (row % 2)
    col = np.floor(shifted)
    mortar = ((y * rows - row) < 0.12) | ((shifted - col) < 0.06)
    base = np.array(_colour(rng, 0.35, 0.8))
    variation = rng.uniform(0.75, 1.1, (rows + 1, cols + 2))[row.astype(int), col.astype(int) % (cols + 2)]
    image = base[None, None, :] * variation[..., None]
    image[mortar] = np.array(_colour(rng, 0.6, 0.9))
    return np.clip(image, 0, 1).astype(np.float32)


def _random_texture(rng: np.random.Generator) -> np.ndarray:
    return [stripes_texture, noise_texture, bricks_texture][int(rng.integers(0, 3))](rng)


# ------------------------------------------------------------------------------------------------ recipes

@recipe("diffuse_room", "diffuse boxes and spheres in a room, static ceiling light, slow orbit (the easy case)")
def diffuse_room(rng: np.random.Generator, frames: int) -> AnimatedScene:
    objects = _room(rng, frames) + [_ceiling_light(frames)]
    for i, (x, z) in enumerate(_scattered_positions(rng, 4)):
        if i % 2:
            objects.append(_sphere(f"ball{i}", (x, 0.4, z), 0.4, diffuse(_colour(rng)), frames))
        else:
            half = rng.uniform(0.25, 0.45)
            objects.append(_box(f"box{i}", (x, half, z), (half, half, half), rng.uniform(0, 90),
                                diffuse(_colour(rng)), frames))
    return AnimatedScene("diffuse_room", _orbit_cameras(rng, frames, 10.0), objects)


@recipe("textured_detail", "fine stripes, noise and bricks on every surface, slow sub-pixel pan")
def textured_detail(rng: np.random.Generator, frames: int) -> AnimatedScene:
    objects = _room(rng, frames, floor=ImageTexture(_random_texture(rng), tiles=4.0),
                    wall=ImageTexture(_random_texture(rng), tiles=3.0)) + [_ceiling_light(frames)]
    for i, (x, z) in enumerate(_scattered_positions(rng, 3)):
        half = rng.uniform(0.3, 0.5)
        objects.append(_box(f"box{i}", (x, half, z), (half, half, half), rng.uniform(0, 90),
                            diffuse(ImageTexture(_random_texture(rng), tiles=1.0)), frames))
    return AnimatedScene("textured_detail", _orbit_cameras(rng, frames, 6.0, radius=5.0), objects,
                         sky=(0.1, 0.1, 0.12))


@recipe("metals", "smooth, glossy and rough metal spheres and boxes under a sky and a ceiling light")
def metals(rng: np.random.Generator, frames: int) -> AnimatedScene:
    objects = _room(rng, frames, floor=ImageTexture(noise_texture(rng), tiles=2.0)) + [_ceiling_light(frames)]
    roughnesses = [0.0, 0.15, 0.35, 0.6]
    for i, ((x, z), roughness) in enumerate(zip(_scattered_positions(rng, 4), roughnesses)):
        tint = _colour(rng, 0.55, 0.98)
        if i % 2 == 0:
            objects.append(_sphere(f"metal{i}", (x, 0.45, z), 0.45, metal(tint, roughness), frames))
        else:
            objects.append(_box(f"metal{i}", (x, 0.35, z), (0.35, 0.35, 0.35), rng.uniform(0, 90),
                                metal(tint, roughness), frames))
    objects.append(_sphere("plastic", (0.0, 0.3, 0.0), 0.3, plastic(_colour(rng), 0.3), frames))
    return AnimatedScene("metals", _orbit_cameras(rng, frames, 15.0), objects, sky=(0.3, 0.32, 0.35))


@recipe("glass", "smooth and frosted glass in front of a textured wall and checker floor")
def glass_scene(rng: np.random.Generator, frames: int) -> AnimatedScene:
    checker = np.kron((np.indices((16, 16)).sum(axis=0) % 2), np.ones((8, 8)))[..., None]
    floor = (0.15 + 0.7 * checker * np.ones(3)).astype(np.float32)
    objects = _room(rng, frames, floor=ImageTexture(floor, tiles=2.0),
                    wall=ImageTexture(_random_texture(rng), tiles=2.0)) + [_ceiling_light(frames, power=15.0)]
    positions = _scattered_positions(rng, 3, extent=1.0)
    objects.append(_sphere("glass_ball", (positions[0][0], 0.5, positions[0][1]), 0.5, glass(0.0), frames))
    objects.append(_box("frosted_box", (positions[1][0], 0.4, positions[1][1]), (0.4, 0.4, 0.4),
                        rng.uniform(0, 90), glass(0.3), frames))
    objects.append(_sphere("coloured_ball", (positions[2][0], 0.3, positions[2][1]), 0.3,
                           plastic(_colour(rng), 0.2), frames))
    return AnimatedScene("glass", _orbit_cameras(rng, frames, 12.0, radius=5.0), objects, sky=(0.2, 0.2, 0.22))


@recipe("moving_light", "static camera, a small light circling the objects: shadows move, accumulation fails")
def moving_light(rng: np.random.Generator, frames: int) -> AnimatedScene:
    objects = _room(rng, frames)
    for i, (x, z) in enumerate(_scattered_positions(rng, 3, extent=1.0)):
        material = plastic(_colour(rng), 0.4) if i % 2 else diffuse(_colour(rng))
        objects.append(_box(f"box{i}", (x, 0.35, z), (0.35, 0.35, 0.35), rng.uniform(0, 90), material, frames))
    start, turns = rng.uniform(0, 360), rng.uniform(0.5, 1.0)
    light_path = []
    for t in _progress(frames):
        angle = np.radians(start + 360 * turns * t)
        light_path.append(compose(translate(1.6 * np.sin(angle), 1.6, 1.6 * np.cos(angle)), scale(0.12)))
    objects.append(SceneObject("moving_light", "sphere", light_path, diffuse((0.0, 0.0, 0.0)),
                               emission=(60.0, 55.0, 45.0)))
    camera = Camera((rng.uniform(-1, 1), 2.5, 6.0), (0.0, 0.6, 0.0), (0.0, 1.0, 0.0), 50.0)
    return AnimatedScene("moving_light", [camera] * frames, objects, sky=(0.02, 0.02, 0.03))


@recipe("swinging_light", "a lamp swings across a room over a slow camera orbit: lighting changes, history misleads")
def swinging_light(rng: np.random.Generator, frames: int) -> AnimatedScene:
    # Teaches what moving_light tests (lighting that changes under valid geometry) with another motion, room
    # and camera, so that the held-out moving_light recipe stays unseen in training.
    objects = _room(rng, frames, wall=ImageTexture(_random_texture(rng), tiles=2.0))
    for i, (x, z) in enumerate(_scattered_positions(rng, 4)):
        if i % 2:
            objects.append(_sphere(f"ball{i}", (x, 0.35, z), 0.35, plastic(_colour(rng), 0.3), frames))
        else:
            half = rng.uniform(0.25, 0.45)
            objects.append(_box(f"box{i}", (x, half, z), (half, half, half), rng.uniform(0, 90),
                                diffuse(_colour(rng)), frames))
    swing, phase = rng.uniform(1.2, 1.8), rng.uniform(0, 2 * np.pi)
    cycles = rng.uniform(0.6, 1.2)
    light_path = []
    for t in _progress(frames):
        x = swing * np.sin(phase + 2 * np.pi * cycles * t)
        light_path.append(compose(translate(x, 2.4 + 0.3 * np.cos(phase + 2 * np.pi * cycles * t), 0.3),
                                  scale(0.15)))
    objects.append(SceneObject("swinging_light", "sphere", light_path, diffuse((0.0, 0.0, 0.0)),
                               emission=(45.0, 42.0, 36.0)))
    return AnimatedScene("swinging_light", _orbit_cameras(rng, frames, 8.0), objects, sky=(0.03, 0.03, 0.04))


@recipe("moving_object", "a box slides across a textured wall, disoccluding it, under a static camera")
def moving_object(rng: np.random.Generator, frames: int) -> AnimatedScene:
    objects = _room(rng, frames, wall=ImageTexture(_random_texture(rng), tiles=3.0)) + [_ceiling_light(frames)]
    direction = 1 if rng.uniform() < 0.5 else -1
    speed = rng.uniform(2.0, 3.0)
    path = []
    for t in _progress(frames):
        x = direction * speed * (t - 0.5)
        path.append(compose(translate(x, 0.6, -0.6), rotate((0, 1, 0), 60 * t), scale(0.45, 0.6, 0.45)))
    objects.append(SceneObject("slider", "cube", path, plastic(ImageTexture(_random_texture(rng)), 0.25)))
    objects.append(_sphere("still_ball", (rng.uniform(-1, 1), 0.35, 1.0), 0.35, diffuse(_colour(rng)), frames))
    camera = Camera((0.0, 1.6, 5.5), (0.0, 1.0, 0.0), (0.0, 1.0, 0.0), 55.0)
    return AnimatedScene("moving_object", [camera] * frames, objects, sky=(0.05, 0.05, 0.06))


@recipe("fast_camera", "fast camera sweep across a textured room: motion of tens of pixels per frame")
def fast_camera(rng: np.random.Generator, frames: int) -> AnimatedScene:
    objects = _room(rng, frames, floor=ImageTexture(_random_texture(rng), tiles=3.0)) + [_ceiling_light(frames)]
    for i, (x, z) in enumerate(_scattered_positions(rng, 4)):
        objects.append(_sphere(f"ball{i}", (x, 0.35, z), 0.35,
                               plastic(_colour(rng), 0.3) if i % 2 else diffuse(_colour(rng)), frames))
    # Angle per frame is fixed (not per sequence), so short sequences are as fast as long ones.
    degrees_per_frame = rng.uniform(4.0, 7.0)
    return AnimatedScene("fast_camera", _orbit_cameras(rng, frames, degrees_per_frame * (frames - 1)), objects)


@recipe("dark_fireflies", "a dark room lit by one tiny, very bright light over glossy surfaces: fireflies")
def dark_fireflies(rng: np.random.Generator, frames: int) -> AnimatedScene:
    objects = _room(rng, frames, floor=(0.5, 0.5, 0.5))
    objects[0].material = plastic((0.3, 0.3, 0.3), 0.1)  # a glossy floor reflects the tiny light's caustics
    for i, (x, z) in enumerate(_scattered_positions(rng, 3, extent=1.0)):
        objects.append(_sphere(f"metal{i}", (x, 0.35, z), 0.35, metal(_colour(rng, 0.6, 0.95), 0.1 + 0.1 * i),
                               frames))
    light = compose(translate(rng.uniform(-1, 1), 3.0, rng.uniform(-1, 0)), scale(0.04))
    objects.append(SceneObject("tiny_light", "sphere", _static(light, frames), diffuse((0.0, 0.0, 0.0)),
                               emission=(2500.0, 2300.0, 2000.0)))
    return AnimatedScene("dark_fireflies", _orbit_cameras(rng, frames, 8.0), objects)


@recipe("camera_cut", "two views of one room with a hard camera cut half-way: history must be dropped")
def camera_cut(rng: np.random.Generator, frames: int) -> AnimatedScene:
    base = diffuse_room(rng, frames)
    cut = frames // 2
    # The second shot looks down from the opposite front corner, so little of the first view stays in frame.
    second = []
    for t in _progress(frames):
        angle = np.radians(40 - 8 * t)
        second.append(Camera((-3.2 * np.sin(angle), 3.2, 3.2 * np.cos(angle)), (0.3, 0.3, -0.3),
                             (0.0, 1.0, 0.0), 55.0))
    cameras = base.cameras[:cut] + second[cut:]
    return AnimatedScene("camera_cut", cameras, base.objects, base.sky, frozenset({cut}) if cut > 0 else frozenset())


# ------------------------------------------------------------------- failure modes of temporal reuse
# Each recipe below makes history wrong on purpose, so a temporal method must learn (or be tested on) rejecting
# it: a visible light that moves, a light that jumps tens of degrees a frame, objects sliding over fine texture,
# highlights that slide over glossy surfaces.

def _fine_texture(rng: np.random.Generator) -> np.ndarray:
    """Stripes, bricks or a fine checker: the textures a ghost or a blur is most visible on."""
    choice = int(rng.integers(0, 3))
    if choice == 0:
        return stripes_texture(rng)
    if choice == 1:
        return bricks_texture(rng)
    cells = int(rng.integers(24, 48))
    checker = (np.indices((cells, cells)).sum(axis=0) % 2).astype(np.float64)
    image = np.kron(checker, np.ones((256 // cells + 1, 256 // cells + 1)))[:256, :256, None]
    a, b = np.array(_colour(rng, 0.05, 0.3)), np.array(_colour(rng, 0.6, 0.95))
    return (a * (1 - image) + b * image).astype(np.float32)


@recipe("visible_emitter", "a bright lamp, directly visible, crosses the frame in front of a textured wall")
def visible_emitter(rng: np.random.Generator, frames: int) -> AnimatedScene:
    objects = _room(rng, frames, wall=ImageTexture(_fine_texture(rng), tiles=2.0))
    objects.append(_ceiling_light(frames, power=4.0))
    for i, (x, z) in enumerate(_scattered_positions(rng, 2, extent=1.2)):
        objects.append(_box(f"box{i}", (x, 0.3, z + 0.6), (0.3, 0.3, 0.3), rng.uniform(0, 90),
                            plastic(_colour(rng), 0.3), frames))
    direction = 1 if rng.uniform() < 0.5 else -1
    height, depth = rng.uniform(1.0, 1.8), rng.uniform(-1.2, -0.4)
    path = []
    for t in _progress(frames):
        x = direction * 3.0 * (t - 0.5)
        path.append(compose(translate(x, height + 0.2 * np.sin(3 * t), depth), scale(0.18)))
    objects.append(SceneObject("lamp", "sphere", path, diffuse((0.0, 0.0, 0.0)), emission=(40.0, 36.0, 30.0)))
    camera = Camera((rng.uniform(-0.5, 0.5), 1.5, 5.0), (0.0, 1.1, 0.0), (0.0, 1.0, 0.0), 55.0)
    return AnimatedScene("visible_emitter", [camera] * frames, objects, sky=(0.02, 0.02, 0.03))


@recipe("orbiting_light", "a small bright light orbits the objects at 20-50 degrees a frame over a slow camera")
def orbiting_light(rng: np.random.Generator, frames: int) -> AnimatedScene:
    objects = _room(rng, frames, floor=ImageTexture(_random_texture(rng), tiles=3.0))
    for i, (x, z) in enumerate(_scattered_positions(rng, 3, extent=1.1)):
        material = [diffuse(_colour(rng)), plastic(_colour(rng), 0.3), metal(_colour(rng, 0.6, 0.95), 0.3)][i]
        objects.append(_sphere(f"ball{i}", (x, 0.35, z), 0.35, material, frames))
    start = rng.uniform(0, 360)
    degrees_per_frame = rng.uniform(20.0, 50.0) * (1 if rng.uniform() < 0.5 else -1)
    radius, height = rng.uniform(1.0, 1.8), rng.uniform(0.9, 2.0)
    path = []
    for index in range(frames):
        angle = np.radians(start + degrees_per_frame * index)
        path.append(compose(translate(radius * np.sin(angle), height, radius * np.cos(angle)), scale(0.08)))
    objects.append(SceneObject("orbiting_light", "sphere", path, diffuse((0.0, 0.0, 0.0)),
                               emission=(150.0, 140.0, 120.0)))
    return AnimatedScene("orbiting_light", _orbit_cameras(rng, frames, 6.0, radius=5.5), objects,
                         sky=(0.02, 0.02, 0.03))


@recipe("sliding_over_texture", "spheres and boxes slide fast over a finely textured floor and wall")
def sliding_over_texture(rng: np.random.Generator, frames: int) -> AnimatedScene:
    objects = _room(rng, frames, floor=ImageTexture(_fine_texture(rng), tiles=4.0),
                    wall=ImageTexture(_fine_texture(rng), tiles=3.0)) + [_ceiling_light(frames)]
    for i in range(2):
        speed = rng.uniform(1.5, 3.0) * (1 if rng.uniform() < 0.5 else -1)
        z, radius = rng.uniform(-1.0, 0.8), rng.uniform(0.25, 0.4)
        y = radius if i == 0 else rng.uniform(0.8, 1.6)  # one rolls on the floor, one flies past the wall
        path = [compose(translate(speed * (t - 0.5), y, z), rotate((0, 0, 1), -200 * speed * t), scale(radius))
                for t in _progress(frames)]
        material = plastic(ImageTexture(_random_texture(rng)), 0.3) if i else diffuse(_colour(rng))
        objects.append(SceneObject(f"slider{i}", "sphere" if i == 0 else "cube", path, material))
    camera = Camera((rng.uniform(-1, 1), 1.8, 5.0), (0.0, 0.6, 0.0), (0.0, 1.0, 0.0), 55.0)
    return AnimatedScene("sliding_over_texture", [camera] * frames, objects, sky=(0.05, 0.05, 0.06))


@recipe("moving_highlights", "a visible light glides over glossy metal and plastic: highlights slide every frame")
def moving_highlights(rng: np.random.Generator, frames: int) -> AnimatedScene:
    objects = _room(rng, frames, floor=(0.3, 0.3, 0.3))
    objects[0].material = plastic(_colour(rng, 0.2, 0.5), 0.15)
    for i, (x, z) in enumerate(_scattered_positions(rng, 4, extent=1.2)):
        roughness = rng.uniform(0.05, 0.35)
        material = metal(_colour(rng, 0.6, 0.95), roughness) if i % 2 else plastic(_colour(rng), roughness)
        objects.append(_sphere(f"glossy{i}", (x, 0.4, z), 0.4, material, frames))
    start, end = rng.uniform(-1.5, -0.5, 2), rng.uniform(0.5, 1.5, 2)
    height = rng.uniform(1.2, 2.2)
    path = [compose(translate(start[0] + (end[0] - start[0]) * t, height, start[1] + (end[1] - start[1]) * t),
                    scale(0.12)) for t in _progress(frames)]
    objects.append(SceneObject("glide_light", "sphere", path, diffuse((0.0, 0.0, 0.0)),
                               emission=(60.0, 58.0, 50.0)))
    return AnimatedScene("moving_highlights", _orbit_cameras(rng, frames, 8.0), objects, sky=(0.1, 0.1, 0.12))
