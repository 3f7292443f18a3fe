"""Render noisy 1spp frames and high-sample references with Blender Cycles, ready for ``denoiser import``.

Needs Blender as a Python module (``pip install -e '.[blender]'``), run with the project's Python:

    python scripts/render_blender.py --out renders/room --frames 8 --size 64 --ref-spp 256
    python scripts/render_blender.py --blend my_scene.blend --frame-start 1 --frames 24 --out renders/mine
    denoiser import --layout blender-cycles renders/room --out data/blender

Writes OUT/frame_NNNN.exr (noisy) and OUT/references/frame_NNNN.exr as Blender writes them (multilayer EXR, one
part per pass, channels ``ViewLayer.<Pass>.<component>``): the ``blender-cycles`` layout reads them as they are.
Each file's metadata note (header attribute ``Note``) is ``fov_y_degrees=...`` (and ``jitter=X,Y`` with ``--jitter
halton``). OUT/cameras.json records every frame's camera. Noisy frames take 1 sample at the pixel centre with
Blender's denoiser off; the guides are first-hit passes, noise-free at 1 spp; references are box-filtered pixel
averages; motion blur is off. A user's ``.blend`` keeps its camera, objects and animation: only the render settings
change, in memory. Why each setting: docs/generating-data.md, "scripts/render_blender.py: why these settings".
"""

from __future__ import annotations

import argparse
import json
import math
import random
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the project, when run as a script
from model.data.camera import frame_jitter  # noqa: E402  (NumPy only)

try:
    import bpy
except ImportError:  # pragma: no cover - only without the optional extra
    sys.exit("scripts/render_blender.py needs Blender as a Python module: pip install -e '.[blender]'")


SCENES = ("orbit", "pan", "moving_object", "room_dolly", "room_light")


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True, type=Path, help="output folder (references/ inside)")
    parser.add_argument("--blend", type=Path, help="a .blend scene to render (default: a procedural scene)")
    parser.add_argument("--scene", choices=SCENES, default="orbit",
                        help="procedural scene: camera orbit, camera pan, or a static camera and a moving cube (an "
                             "open floor under sun and sky), or a closed room under a point light with the camera "
                             "moving in (room_dolly) or the light circling (room_light)")
    parser.add_argument("--frames", type=int, default=4, help="number of frames")
    parser.add_argument("--frame-start", type=int, default=1, help="first frame of the .blend's timeline to render")
    parser.add_argument("--size", default="64", help="render resolution N or WxH")
    parser.add_argument("--ref-spp", type=int, default=128, help="samples per pixel of the references (0: none)")
    parser.add_argument("--ref-scale", type=int, choices=(1, 2), default=1,
                        help="references at this multiple of --size (2: for evaluating 2x upscaling)")
    parser.add_argument("--seed", type=int, default=0, help="varies the procedural scene and the noise")
    parser.add_argument("--max-bounces", type=int, default=6, help="Cycles' total bounce limit")
    parser.add_argument("--jitter", choices=("none", "halton"), default="none",
                        help="where each noisy frame's one sample sits in its pixel: 'none' (default) the pixel "
                             "centre; 'halton' a TAA jitter per frame (Halton(2, 3) of the frame index + 1, minus "
                             "0.5; a camera shift, stamped into the note), which lets the fused 2x models gather "
                             "detail finer than a pixel (README: 'Jittered Blender frames')")
    args = parser.parse_args(argv)
    width, _, height = args.size.partition("x")
    args.width, args.height = int(width), int(height or width)
    if args.frames < 1 or args.width < 1 or args.height < 1 or args.ref_spp < 0:
        parser.error("--frames and --size must be positive and --ref-spp >= 0")
    if args.blend is not None and not args.blend.is_file():
        parser.error(f"--blend {args.blend}: file not found")
    return args


# --- procedural scenes ------------------------------------------------------------------------------------


def _material(name: str, color: tuple[float, float, float], roughness: float, metallic: float = 0.0,
              checker: float = 0.0):
    """A Principled BSDF; ``checker`` > 0: a checker of that many cells per unit (texture that shows motion)."""
    material = bpy.data.materials.new(name)
    material.use_nodes = True
    nodes = material.node_tree.nodes
    bsdf = nodes["Principled BSDF"]
    bsdf.inputs["Base Color"].default_value = (*color, 1.0)
    if checker:
        texture = nodes.new("ShaderNodeTexChecker")
        texture.inputs["Scale"].default_value = checker
        texture.inputs["Color1"].default_value = (*color, 1.0)
        texture.inputs["Color2"].default_value = (*(0.25 * c for c in color), 1.0)
        coordinates = nodes.new("ShaderNodeTexCoord")
        material.node_tree.links.new(coordinates.outputs["Object"], texture.inputs["Vector"])
        material.node_tree.links.new(texture.outputs["Color"], bsdf.inputs["Base Color"])
    bsdf.inputs["Roughness"].default_value = roughness
    bsdf.inputs["Metallic"].default_value = metallic
    return material


def _add(primitive, material, **kwargs):
    primitive(**kwargs)
    obj = bpy.context.active_object
    obj.data.materials.append(material)
    return obj


def _tracking_camera(scene, frames: int, lens: float, target: tuple[float, float, float]):
    """The scene's camera for frames 1..``frames``, always turned towards ``target`` (a track-to constraint)."""
    bpy.ops.object.camera_add()
    camera = bpy.context.active_object
    camera.data.lens = lens
    scene.camera = camera
    scene.frame_start, scene.frame_end = 1, frames
    track = camera.constraints.new("TRACK_TO")
    bpy.ops.object.empty_add(location=target)
    track.target = bpy.context.active_object
    return camera


def _noise_material(name: str, color: tuple[float, float, float], roughness: float, scale: float):
    """A Principled BSDF whose colour is Blender's noise texture between 0.3 x ``color`` and ``color``."""
    material = bpy.data.materials.new(name)
    material.use_nodes = True
    nodes = material.node_tree.nodes
    bsdf = nodes["Principled BSDF"]
    texture = nodes.new("ShaderNodeTexNoise")
    texture.inputs["Scale"].default_value = scale
    ramp = nodes.new("ShaderNodeValToRGB")
    ramp.color_ramp.elements[0].color = (*(0.3 * c for c in color), 1.0)
    ramp.color_ramp.elements[1].color = (*color, 1.0)
    material.node_tree.links.new(texture.outputs["Fac"], ramp.inputs["Fac"])
    material.node_tree.links.new(ramp.outputs["Color"], bsdf.inputs["Base Color"])
    bsdf.inputs["Roughness"].default_value = roughness
    return material


def build_room_scene(kind: str, frames: int, seed: int) -> None:
    """A closed room (noise-textured walls, floor and ceiling) with boxes and spheres under one point light and a
    dim world: the camera moves in (``room_dolly``) or stands while the light circles (``room_light``). A scene
    style unlike the open floors above, for training models on Cycles' frames without their recipes."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    rng = random.Random(seed)
    scene = bpy.context.scene

    def colour() -> tuple[float, float, float]:
        return tuple(rng.uniform(0.2, 0.85) for _ in range(3))

    _add(bpy.ops.mesh.primitive_plane_add, _noise_material("floor", colour(), 0.6, rng.uniform(4, 12)), size=10.0)
    walls = [((0, 5, 2.5), (math.pi / 2, 0, 0)), ((-5, 0, 2.5), (0, math.pi / 2, 0)),
             ((5, 0, 2.5), (0, math.pi / 2, 0)), ((0, 0, 5), (0, 0, 0)), ((0, -5, 2.5), (math.pi / 2, 0, 0))]
    for index, (location, rotation) in enumerate(walls):
        wall = _noise_material(f"wall{index}", colour(), 0.8, rng.uniform(2, 20))
        _add(bpy.ops.mesh.primitive_plane_add, wall, size=10.0, location=location, rotation=rotation)
    for index in range(4):
        material = _material(f"object{index}", colour(), rng.uniform(0.1, 0.9), metallic=float(rng.random() < 0.3),
                             checker=rng.choice([0.0, 0.0, 3.0]))
        if rng.random() < 0.5:
            size = rng.uniform(0.5, 1.0)
            location = (rng.uniform(-2.5, 2.5), rng.uniform(-1, 3), size / 2)
            _add(bpy.ops.mesh.primitive_cube_add, material, size=size, location=location,
                 rotation=(0, 0, rng.uniform(0, math.pi)))
        else:
            radius = rng.uniform(0.3, 0.7)
            location = (rng.uniform(-2.5, 2.5), rng.uniform(-1, 3), radius)
            _add(bpy.ops.mesh.primitive_uv_sphere_add, material, radius=radius, location=location)
    bpy.ops.object.light_add(type="POINT", location=(rng.uniform(-2, 2), rng.uniform(-1, 2), 3.5))
    light = bpy.context.active_object
    light.data.energy = rng.uniform(400, 900)
    light.data.shadow_soft_size = 0.2
    world = bpy.data.worlds.new("dim")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.05
    scene.world = world

    camera = _tracking_camera(scene, frames, lens=22.0, target=(0.0, 1.5, 0.8))
    phase = rng.uniform(0, 2 * math.pi)
    for frame in range(1, frames + 1):
        t = frame - 1
        if kind == "room_dolly":
            camera.location = (0.8 * math.cos(phase) + 0.05 * t, -4.2 + 0.15 * t, 1.6 + 0.03 * t)
        else:
            camera.location = (0.5, -4.2, 1.8)
        camera.keyframe_insert("location", frame=frame)
        if kind == "room_light":
            light.location = (2.5 * math.cos(phase + 0.35 * t), 1 + 2.0 * math.sin(phase + 0.35 * t), 3.2)
            light.keyframe_insert("location", frame=frame)
    _linear_keyframes()


def _linear_keyframes() -> None:
    # Linear interpolation: constant speed, so the motion between frames is the same everywhere in the clip.
    for action in bpy.data.actions:
        for curve in _fcurves(action):
            for point in curve.keyframe_points:
                point.interpolation = "LINEAR"


def build_procedural_scene(kind: str, frames: int, seed: int) -> None:
    """A floor, a back wall, boxes and a sphere under a sun and a sky, with the camera or a cube animated."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    rng = random.Random(seed)
    scene = bpy.context.scene
    floor = _material("floor", (0.8, 0.75, 0.7), 0.9, checker=0.8)
    _add(bpy.ops.mesh.primitive_plane_add, floor, size=40.0, location=(0.0, 0.0, 0.0))
    wall = _material("wall", (0.4, 0.6, 0.8), 0.8, checker=1.2)
    _add(bpy.ops.mesh.primitive_plane_add, wall, size=40.0, location=(0.0, 6.0, 0.0), rotation=(math.pi / 2, 0, 0))
    for index in range(3):
        colour = tuple(rng.uniform(0.15, 0.85) for _ in range(3))
        box = _material(f"box{index}", colour, rng.uniform(0.2, 0.9))
        size = rng.uniform(0.6, 1.2)
        _add(bpy.ops.mesh.primitive_cube_add, box, size=size,
             location=(rng.uniform(-2.5, 2.5), rng.uniform(-0.5, 2.5), size / 2),
             rotation=(0.0, 0.0, rng.uniform(0, math.pi)))
    metal = _material("metal", (0.9, 0.8, 0.6), 0.25, metallic=1.0)
    _add(bpy.ops.mesh.primitive_uv_sphere_add, metal, radius=0.7, location=(rng.uniform(-1, 1), 0.5, 0.7))

    bpy.ops.object.light_add(type="SUN", rotation=(math.radians(40), math.radians(15), math.radians(30)))
    bpy.context.active_object.data.energy = 3.0
    world = bpy.data.worlds.new("sky")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.4, 0.5, 0.7, 1.0)
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.6
    scene.world = world

    camera = _tracking_camera(scene, frames, lens=30.0, target=(0.0, 1.0, 0.6))
    for frame in range(1, frames + 1):
        t = frame - 1
        if kind == "orbit":
            angle = math.radians(-90 + 4.0 * t)
            camera.location = (7.0 * math.cos(angle), 1.0 + 7.0 * math.sin(angle), 2.5)
        elif kind == "pan":
            camera.location = (-1.0 + 0.3 * t, -6.0, 2.0 + 0.1 * t)
        else:
            camera.location = (0.5, -6.5, 2.2)
        camera.keyframe_insert("location", frame=frame)
    if kind == "moving_object":
        cube = _add(bpy.ops.mesh.primitive_cube_add, _material("mover", (0.9, 0.3, 0.1), 0.5, checker=5.0), size=1.2)
        for frame in range(1, frames + 1):
            cube.location = (-1.5 + 0.5 * (frame - 1), -1.5, 0.6)
            cube.keyframe_insert("location", frame=frame)
    _linear_keyframes()


def _fcurves(action):
    if hasattr(action, "fcurves") and len(action.fcurves):
        return action.fcurves
    curves = []  # Blender 5 keeps them in layered actions: layers -> strips -> channelbags
    for layer in getattr(action, "layers", ()):
        for strip in layer.strips:
            for bag in strip.channelbags:
                curves.extend(bag.fcurves)
    return curves


# --- render settings --------------------------------------------------------------------------------------


def configure(scene, width: int, height: int, max_bounces: int) -> None:
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    scene.render.use_motion_blur = False  # the Vector pass exists only without motion blur
    scene.render.use_persistent_data = False
    scene.cycles.use_denoising = False
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.max_bounces = max_bounces
    scene.cycles.use_animated_seed = True
    settings = scene.render.image_settings
    if hasattr(settings, "media_type"):  # Blender 5
        settings.media_type = "MULTI_LAYER_IMAGE"
    settings.file_format = "OPEN_EXR_MULTILAYER"
    settings.color_depth = "32"
    settings.exr_codec = "ZIP"
    for layer in scene.view_layers:
        layer.use_pass_combined = True
        layer.use_pass_z = True
        layer.use_pass_normal = True
        layer.use_pass_vector = True
        layer.use_pass_diffuse_color = True
        layer.use_pass_glossy_color = True


def render(scene, path: Path, frame: int, samples: int, reference: bool, ref_scale: int = 1,
           jitter: tuple[float, float] = (0.0, 0.0)) -> None:
    scene.frame_set(frame)
    scene.render.use_stamp_note = True  # written as the header attribute 'Note'
    note = f"fov_y_degrees={math.degrees(camera_fov(scene)[1]):.6f}"
    if jitter != (0.0, 0.0):
        note += f" jitter={jitter[0]:.6f},{jitter[1]:.6f}"
    scene.render.stamp_note_text = note
    scene.cycles.samples = samples
    # Reference: box filter of one pixel (the pixel average). Noisy frame: the narrowest filter Cycles allows,
    # which puts the one sample at the pixel centre.
    scene.cycles.pixel_filter_type = "BOX" if reference else "GAUSSIAN"
    scene.cycles.filter_width = 1.0 if reference else 0.01
    # A 2x reference: the same camera at twice the resolution, each pixel the average over its own (quarter) square;
    # its 2x2 mean is then the 1x reference (the import derives it).
    scene.render.resolution_percentage = 100 * ref_scale if reference else 100
    scene.render.filepath = str(path)
    camera = scene.camera.data
    shift = camera.shift_x, camera.shift_y  # the scene's own (possibly animated) shift, restored after
    per_pixel = shift_per_pixel(scene)
    # x right and y down in the frame bundle; Blender's shift moves the view right and up.
    camera.shift_x, camera.shift_y = shift[0] + jitter[0] * per_pixel, shift[1] - jitter[1] * per_pixel
    try:
        bpy.ops.render.render(write_still=True)
    finally:
        camera.shift_x, camera.shift_y = shift


def shift_per_pixel(scene) -> float:
    """Blender's camera shift that moves the view by one pixel: shift is a fraction of the fitted sensor side."""
    camera = scene.camera.data
    width, height = scene.render.resolution_x, scene.render.resolution_y
    fit = camera.sensor_fit
    side = width if fit == "HORIZONTAL" else height if fit == "VERTICAL" else max(width, height)
    return 1.0 / side


def camera_fov(scene) -> tuple[float, float]:
    """The full (horizontal, vertical) field of view of the scene's camera in radians, sensor fit applied."""
    camera = scene.camera
    width, height = scene.render.resolution_x, scene.render.resolution_y
    horizontal = camera.data.sensor_fit == "HORIZONTAL" or (camera.data.sensor_fit == "AUTO" and width >= height)
    if horizontal:
        fov_x = camera.data.angle_x
        fov_y = 2 * math.atan(math.tan(fov_x / 2) * height / width)
    else:
        fov_y = camera.data.angle_y if camera.data.sensor_fit == "VERTICAL" else camera.data.angle_x
        fov_x = 2 * math.atan(math.tan(fov_y / 2) * width / height)
    return fov_x, fov_y


def camera_record(scene, index: int) -> dict:
    """The camera of the current frame: where it is and how it projects (for checks against known geometry)."""
    camera = scene.camera
    width, height = scene.render.resolution_x, scene.render.resolution_y
    fov_x, fov_y = camera_fov(scene)
    return {
        "frame": index,
        "blender_frame": scene.frame_current,
        "matrix_world": [list(row) for row in camera.matrix_world],  # columns: right, up, backward, position
        # The full field of view across the image's width and height (sensor fit applied).
        "fov_x": fov_x,
        "fov_y": fov_y,
        "width": width,
        "height": height,
    }


def main(argv: list[str]) -> None:
    args = parse_args(argv)
    if args.blend is not None:
        bpy.ops.wm.open_mainfile(filepath=str(args.blend))
        first = args.frame_start
    else:
        build = build_room_scene if args.scene.startswith("room_") else build_procedural_scene
        build(args.scene, args.frames, args.seed)
        first = 1
    scene = bpy.context.scene
    configure(scene, args.width, args.height, args.max_bounces)
    scene.cycles.seed = args.seed
    noisy, references = args.out, args.out / "references"
    noisy.mkdir(parents=True, exist_ok=True)
    if args.ref_spp:
        references.mkdir(parents=True, exist_ok=True)
    cameras = []
    for index in range(args.frames):
        name = f"frame_{index:04d}.exr"
        jitter = frame_jitter(index) if args.jitter == "halton" else (0.0, 0.0)
        render(scene, noisy / name, first + index, 1, reference=False, jitter=jitter)
        cameras.append({**camera_record(scene, index), "jitter": list(jitter)})
        if args.ref_spp:
            render(scene, references / name, first + index, args.ref_spp, reference=True, ref_scale=args.ref_scale)
        print(f"frame {index + 1}/{args.frames}: {noisy / name}", flush=True)
    # Not needed by the import (it skips non-EXR files); kept for checks against known geometry.
    (args.out / "cameras.json").write_text(json.dumps(cameras, indent=1) + "\n")


if __name__ == "__main__":
    main(sys.argv[1:])
