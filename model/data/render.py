"""Rendering one animated scene into frame bundles with Mitsuba 3.

`mi.render` cannot place one sample at a chosen position per pixel, nor split diffuse from specular radiance,
so the noisy frame comes from a short path tracer here (next-event estimation with MIS, Russian roulette, the
same depth semantics as Mitsuba's `path` integrator, whose `mi.render` makes the references). Everything is
computed from the camera sample at (x + 0.5 + jitter_x, y + 0.5 + jitter_y): the radiance, the guide buffers
from the first hit, and motion vectors from the previous frame's camera and object transforms. The reference
albedos average the same first-hit albedo definitions over `albedo_spp` uniformly random positions in each target
pixel, the box filter of the radiance references.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass

import numpy as np

from model.data.camera import Camera, frame_jitter
from model.data.mitsuba_backend import load_mitsuba
from model.data.scenes import AnimatedScene, ImageTexture, Material
from model.data.transforms import apply_to_points
from model.io.frames import FrameBundle, box_downsample

# Sky pixels have no surface point; their motion is that of a point this far along the view ray.
SKY_DISTANCE = 1.0e4
# Most primary rays traced in one wavefront for the reference albedos (Dr.Jit keeps every lane's surface
# interaction in memory, a few hundred bytes each); more samples are traced in several passes.
MAX_ALBEDO_LANES = 1 << 21


@dataclass(frozen=True)
class RenderSettings:
    width: int = 128
    height: int = 128
    ref_spp: int = 1024
    # Target scales of the references; a scale-1 reference is the 2x2 mean of the scale-2 one when both exist.
    ref_scales: tuple[int, ...] = (1, 2)
    # Uniformly random first-hit samples per pixel of the largest reference scale for the reference albedos.
    albedo_spp: int = 16
    max_depth: int = 6
    rr_depth: int = 5
    variant: str | None = None
    # False: every frame's sample at the pixel centre, as renderers without TAA jitter write them (Blender's
    # Cycles frames, for one), so models can be trained and measured on such sequences too.
    jitter: bool = True

    def __post_init__(self) -> None:
        if self.width < 1 or self.height < 1:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        if self.ref_spp < 1:
            raise ValueError(f"ref_spp must be >= 1, got {self.ref_spp}")
        if self.albedo_spp < 1:
            raise ValueError(f"albedo_spp must be >= 1, got {self.albedo_spp}")
        if not self.ref_scales or any(s not in (1, 2, 4) for s in self.ref_scales):
            raise ValueError(f"ref_scales must be a non-empty subset of (1, 2, 4), got {self.ref_scales}")
        if self.max_depth < 1:
            raise ValueError(f"max_depth must be >= 1, got {self.max_depth}")


def frame_seed(seed: int, frame_index: int, purpose: str) -> int:
    """A 31-bit seed per (sequence seed, frame, purpose): frames and passes never share random numbers."""
    return zlib.crc32(f"{seed}:{frame_index}:{purpose}".encode()) & 0x7FFFFFFF


class SceneRenderer:
    """Renders the frames of one `AnimatedScene` at fixed settings; one instance per sequence."""

    def __init__(self, scene: AnimatedScene, settings: RenderSettings, seed: int):
        self.scene, self.settings, self.seed = scene, settings, seed
        self.mi = load_mitsuba(settings.variant)
        # scalar_rgb traces one ray at a time: the same path code runs once per pixel from Python (slow, a
        # fallback for machines without LLVM 19); the JIT variants trace every pixel in one wavefront.
        self.scalar = self.mi.variant().startswith("scalar")
        import drjit as dr

        self.dr = dr

    # ------------------------------------------------------------------------------------ scene building

    def _transform(self, matrix: np.ndarray):
        return self.mi.ScalarTransform4f(matrix.tolist())

    def _texture(self, reflectance) -> dict:
        if isinstance(reflectance, ImageTexture):
            return {"type": "bitmap", "bitmap": self.mi.Bitmap(reflectance.pixels), "raw": True,
                    "filter_type": "bilinear", "wrap_mode": "repeat",
                    "to_uv": self.mi.ScalarTransform4f().scale([reflectance.tiles, reflectance.tiles, 1.0])}
        return {"type": "rgb", "value": list(reflectance)}

    def _bsdf(self, material: Material) -> dict:
        alpha = max(material.roughness ** 2, 1e-3)
        reflectance = self._texture(material.reflectance)
        if material.kind == "diffuse":
            return {"type": "diffuse", "reflectance": reflectance}
        if material.kind == "plastic":
            return {"type": "roughplastic", "distribution": "ggx", "alpha": alpha, "int_ior": 1.5,
                    "diffuse_reflectance": reflectance}
        if material.kind == "metal":
            if material.roughness == 0.0:
                return {"type": "conductor", "material": "none", "specular_reflectance": reflectance}
            return {"type": "roughconductor", "material": "none", "distribution": "ggx", "alpha": alpha,
                    "specular_reflectance": reflectance}
        if material.kind == "glass":
            if material.roughness == 0.0:
                return {"type": "dielectric", "int_ior": 1.5}
            return {"type": "roughdielectric", "distribution": "ggx", "alpha": alpha, "int_ior": 1.5}
        raise ValueError(f"unknown material kind {material.kind!r}")

    def _sensor(self, camera: Camera, width: int, height: int, spp: int) -> dict:
        return {"type": "perspective", "fov": camera.fov, "fov_axis": "x", "near_clip": 0.01,
                "far_clip": 2 * SKY_DISTANCE, "to_world": self._transform(camera.to_world()),
                "film": {"type": "hdrfilm", "width": width, "height": height, "pixel_format": "rgb",
                         # A box filter keeps pixel noise independent; Mitsuba's default Gaussian correlates it.
                         "rfilter": {"type": "box"}},
                "sampler": {"type": "independent", "sample_count": spp}}

    def _scene_dict(self, frame_index: int, sensor: dict) -> dict:
        s = self.settings
        scene: dict = {"type": "scene", "sensor": sensor,
                       "integrator": {"type": "path", "max_depth": s.max_depth, "rr_depth": s.rr_depth}}
        if any(c > 0 for c in self.scene.sky):
            scene["sky"] = {"type": "constant", "radiance": {"type": "rgb", "value": list(self.scene.sky)}}
        for obj in self.scene.objects:
            shape = {"type": obj.shape, "to_world": self._transform(obj.transforms[frame_index]),
                     "bsdf": self._bsdf(obj.material)}
            if obj.emission is not None:
                shape["emitter"] = {"type": "area", "radiance": {"type": "rgb", "value": list(obj.emission)}}
            scene[obj.name] = shape
        return scene

    # ------------------------------------------------------------------------------------------ rendering

    def render_frame(self, frame_index: int) -> FrameBundle:
        s, scene = self.settings, self.scene
        camera = scene.cameras[frame_index]
        jitter = frame_jitter(frame_index) if s.jitter else (0.0, 0.0)
        mi_scene = self.mi.load_dict(self._scene_dict(frame_index, self._sensor(camera, s.width, s.height, 1)))
        traced = self._trace_1spp(mi_scene, jitter, frame_seed(self.seed, frame_index, "1spp"))
        motion = self._motion(frame_index, traced, jitter)
        references = self._references(mi_scene, camera, frame_index)
        reference_albedos, reference_specular_albedos = self._reference_albedos(mi_scene, frame_index)
        shape_index = traced["shape_index"]
        roughness_table = self._material_tables()[0]
        hit = shape_index >= 0
        roughness = np.where(hit, roughness_table[np.where(hit, shape_index, 0)], 0.0)
        albedo, specular_albedo = self._guide_albedos(traced["albedo"], shape_index)
        h, w = s.height, s.width
        return FrameBundle(
            color=traced["color"].reshape(h, w, 3), albedo=albedo.reshape(h, w, 3),
            normal=traced["normal"].reshape(h, w, 3), depth=traced["depth"].reshape(h, w),
            motion=motion.reshape(h, w, 2), jitter=jitter, frame_index=frame_index, sequence="",
            camera_cut=frame_index in scene.cuts,
            diffuse=traced["diffuse"].reshape(h, w, 3), specular=traced["specular"].reshape(h, w, 3),
            specular_albedo=specular_albedo.reshape(h, w, 3),
            roughness=roughness.reshape(h, w).astype(np.float32), references=references,
            reference_albedos=reference_albedos, reference_specular_albedos=reference_specular_albedos)

    def _material_tables(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        objects = self.scene.objects
        roughness = np.array([o.material.roughness for o in objects], dtype=np.float32)
        specular = np.array([o.material.specular_albedo for o in objects], dtype=np.float32).reshape(-1, 3)
        has_diffuse = np.array([o.material.kind in ("diffuse", "plastic") for o in objects], dtype=np.float32)
        return roughness, specular, has_diffuse

    def _guide_albedos(self, reflectance: np.ndarray, shape_index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Diffuse and specular albedo of first hits, (N, 3) float32 each, from `_first_hit_guides` output.

        The one definition of both guides: the 1spp buffers and the reference albedos average it.
        """
        _, specular_table, diffuse_table = self._material_tables()
        hit = shape_index >= 0
        safe = np.where(hit, shape_index, 0)
        specular_albedo = np.where(hit[..., None], specular_table[safe], 0.0).astype(np.float32)
        # Mitsuba's diffuse reflectance of metals and glass is not a diffuse albedo: keep it to diffuse lobes.
        albedo = reflectance * np.where(hit, diffuse_table[safe], 0.0)[..., None]
        return np.clip(albedo, 0, 1).astype(np.float32), specular_albedo

    def _reference_albedos(self, mi_scene, frame_index: int) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
        """Box-filtered diffuse and specular albedo at every reference scale: the mean of `albedo_spp` first hits
        at uniformly random positions in each pixel of the largest scale, box-downsampled to the smaller ones."""
        mi, dr, s = self.mi, self.dr, self.settings
        top = max(s.ref_scales)
        width, height = s.width * top, s.height * top
        pixels = width * height
        sums = np.zeros((2, pixels, 3), dtype=np.float64)
        samples_per_pass = max(1, min(s.albedo_spp, MAX_ALBEDO_LANES // pixels))
        pixel = np.arange(pixels)
        for pass_index, first in enumerate(range(0, s.albedo_spp, samples_per_pass)):
            samples = min(samples_per_pass, s.albedo_spp - first)
            seed = frame_seed(self.seed, frame_index, f"albedo:{pass_index}")
            # Uniform positions inside each pixel; lane = sample * pixels + pixel.
            offset = np.random.default_rng(seed).random((samples * pixels, 2))
            film_x = (np.tile(pixel % width, samples) + offset[:, 0]) / width
            film_y = (np.tile(pixel // width, samples) + offset[:, 1]) / height
            guides = self._trace_film(mi_scene, film_x, film_y, seed, max_depth=1, guides_only=True)
            albedo, specular_albedo = self._guide_albedos(guides["albedo"], guides["shape_index"])
            # Summed in float64: identical samples (a flat surface) then average to exactly the 1spp guide value.
            sums[0] += albedo.reshape(samples, pixels, 3).sum(axis=0, dtype=np.float64)
            sums[1] += specular_albedo.reshape(samples, pixels, 3).sum(axis=0, dtype=np.float64)
        albedo, specular_albedo = (sums / s.albedo_spp).astype(np.float32).reshape(2, height, width, 3)
        return ({scale: box_downsample(albedo, top // scale) for scale in s.ref_scales},
                {scale: box_downsample(specular_albedo, top // scale) for scale in s.ref_scales})

    def _references(self, mi_scene, camera: Camera, frame_index: int) -> dict[int, np.ndarray]:
        s = self.settings
        top = max(s.ref_scales)
        sensor = self.mi.load_dict(self._sensor(camera, s.width * top, s.height * top, s.ref_spp))
        image = self.mi.render(mi_scene, sensor=sensor, spp=s.ref_spp,
                               seed=frame_seed(self.seed, frame_index, "reference"))
        image = np.asarray(image, dtype=np.float32)[..., :3]
        return {scale: box_downsample(image, top // scale) for scale in s.ref_scales}

    def _trace_1spp(self, mi_scene, jitter: tuple[float, float], seed: int) -> dict[str, np.ndarray]:
        """One path per pixel at the jittered sample position; returns flat NumPy buffers (H*W, ...)."""
        s = self.settings
        index = np.arange(s.width * s.height)
        sample_x = (index % s.width).astype(np.float64) + 0.5 + jitter[0]
        sample_y = (index // s.width).astype(np.float64) + 0.5 + jitter[1]
        result = self._trace_film(mi_scene, sample_x / s.width, sample_y / s.height, seed, s.max_depth)
        result["diffuse"] = np.maximum(result["diffuse"], 0.0)
        result["specular"] = np.maximum(result["specular"], 0.0)
        result["color"] = result["diffuse"] + result["specular"]
        result["film_position"] = np.stack([sample_x, sample_y], axis=1).astype(np.float32)
        return result

    def _trace_film(self, mi_scene, film_x: np.ndarray, film_y: np.ndarray, seed: int, max_depth: int,
                    guides_only: bool = False) -> dict[str, np.ndarray]:
        """Trace one path of `max_depth` through each film position in [0, 1]^2 (`guides_only`: first hits only).

        Returns NumPy arrays, one row per position: the first hit's guides, diffuse and specular radiance, and
        the camera ray. JIT variants trace all positions as one wavefront; scalar_rgb loops over them, each
        with its own random stream.
        """
        mi = self.mi
        if not self.scalar:
            sampler = mi.load_dict({"type": "independent"})
            sampler.seed(seed, len(film_x))
            film_position = mi.Point2f(mi.Float(film_x.astype(np.float32)), mi.Float(film_y.astype(np.float32)))
            traced = self._trace_rays(mi_scene, sampler, film_position, max_depth, guides_only)
            return {name: _to_numpy(value) for name, value in traced.items()}
        sampler = mi.load_dict({"type": "independent"})
        rows: dict[str, list] = {}
        for lane, (x, y) in enumerate(zip(film_x.tolist(), film_y.tolist())):
            sampler.seed((seed + lane * 0x9E3779B1) & 0xFFFFFFFF, 1)  # the sampler hashes seeds (TEA)
            traced = self._trace_rays(mi_scene, sampler, mi.Point2f(x, y), max_depth, guides_only)
            for name, value in traced.items():
                rows.setdefault(name, []).append(np.asarray(value, dtype=np.float32 if name != "shape_index"
                                                            else np.int32))
        return {name: np.stack(values) for name, values in rows.items()}

    def _trace_rays(self, mi_scene, sampler, film_position, max_depth: int, guides_only: bool) -> dict:
        """The path tracer proper, on Mitsuba types: a wavefront (JIT variants) or one ray (scalar_rgb)."""
        mi, dr, s = self.mi, self.dr, self.settings
        sensor = mi_scene.sensors()[0]  # film positions are in [0, 1]^2: its resolution does not matter
        ray, _ = sensor.sample_ray_differential(0.0, sampler.next_1d(), film_position, mi.Point2f(0.5, 0.5))
        camera_ray = mi.Ray3f(ray)

        ctx = mi.BSDFContext()
        throughput = mi.Spectrum(1.0)
        diffuse, specular = mi.Spectrum(0.0), mi.Spectrum(0.0)
        active = mi.Bool(True)
        first_lobe_diffuse = mi.Bool(False)
        previous_si = dr.zeros(mi.SurfaceInteraction3f)
        previous_pdf, previous_delta = mi.Float(1.0), mi.Bool(True)
        eta = mi.Float(1.0)
        guides = {}
        current = mi.Ray3f(camera_ray)
        for depth in range(max_depth):
            si = mi_scene.ray_intersect(current, ray_flags=mi.RayFlags.All, coherent=depth == 0, active=active)
            # A scalar miss has no shape to ask for a BSDF (Mitsuba would crash); its path ends below anyway.
            bsdf = si.bsdf(current) if not self.scalar or si.is_valid() else None
            if depth == 0:
                guides = self._first_hit_guides(mi_scene, si, bsdf)
                if guides_only:
                    break

            # Emission reached by the sampled direction, MIS-weighted against next-event estimation.
            emitter = si.emitter(mi_scene, active)
            direction_sample = mi.DirectionSample3f(mi_scene, si, previous_si)
            # Scalar variants return no emitter (None) where the hit emits nothing; Mitsuba must not be asked
            # for that direction's pdf then (it dereferences the emitter).
            emitter_pdf = mi.Float(0.0) if depth == 0 or emitter is None else mi_scene.pdf_emitter_direction(
                previous_si, direction_sample, _negate(previous_delta))
            radiance = emitter.eval(si, active) if emitter is not None else mi.Spectrum(0.0)
            emitted = throughput * _mis_weight(dr, previous_pdf, emitter_pdf) * radiance
            # As Mitsuba's film does with invalid samples, a non-finite contribution (0 * inf at a degenerate
            # sample) is dropped rather than poisoning the pixel; the same guard applies to `direct` below.
            emitted = dr.select(active & dr.isfinite(emitted), emitted, 0.0)
            if depth == 0:
                specular += emitted  # seen directly: no lobe was sampled, so it is not diffuse radiance
            else:
                diffuse += dr.select(first_lobe_diffuse, emitted, 0.0)
                specular += dr.select(first_lobe_diffuse, 0.0, emitted)
            if depth + 1 >= max_depth or (self.scalar and not (active and si.is_valid())):
                break

            active_next = active & si.is_valid()
            # Next-event estimation at this vertex.
            active_nee = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
            light_sample, light_weight = mi_scene.sample_emitter_direction(si, sampler.next_2d(), True, active_nee)
            active_nee &= light_sample.pdf != 0.0
            wo = si.to_local(light_sample.d)
            bsdf_value, bsdf_pdf = bsdf.eval_pdf(ctx, si, wo, active_nee)
            nee_mis = dr.select(light_sample.delta, 1.0, _mis_weight(dr, light_sample.pdf, bsdf_pdf))
            direct = dr.select(active_nee, throughput * nee_mis * bsdf_value * light_weight, 0.0)
            direct = dr.select(dr.isfinite(direct), direct, 0.0)

            # Sample the BSDF to continue the path; the first sampled lobe decides the path's buffer.
            sample, weight = bsdf.sample(ctx, si, sampler.next_1d(), sampler.next_2d(), active_next)
            if depth == 0:
                first_lobe_diffuse = mi.has_flag(sample.sampled_type, mi.BSDFFlags.Diffuse)
            diffuse += dr.select(first_lobe_diffuse, direct, 0.0)
            specular += dr.select(first_lobe_diffuse, 0.0, direct)

            throughput *= weight
            eta *= sample.eta
            current = si.spawn_ray(si.to_world(sample.wo))
            previous_si = si
            previous_pdf = sample.pdf
            previous_delta = mi.has_flag(sample.sampled_type, mi.BSDFFlags.Delta)
            active = active_next & (sample.pdf > 0.0) & (dr.max(throughput) > 0.0)
            if depth + 1 >= s.rr_depth:
                survive = dr.minimum(dr.max(throughput) * dr.square(eta), 0.95)
                active &= sampler.next_1d() < survive
                throughput *= dr.select(active, dr.rcp(survive), 0.0)
            if not self.scalar:
                dr.eval(diffuse, specular, throughput, current, active, previous_si, previous_pdf, previous_delta,
                        first_lobe_diffuse, eta)

        return {**guides, "diffuse": diffuse, "specular": specular, "view_direction": camera_ray.d,
                "camera_origin": camera_ray.o}

    def _first_hit_guides(self, mi_scene, si, bsdf) -> dict:
        mi, dr = self.mi, self.dr
        valid = si.is_valid()
        shape_names = [obj.name for obj in self.scene.objects]
        if self.scalar:  # one ray: the hit shape is an object (or nothing)
            shape_index = shape_names.index(si.shape.id()) if valid else -1
            if not valid:
                return {"depth": 0.0, "normal": mi.Vector3f(0.0), "albedo": mi.Color3f(0.0), "position": si.p,
                        "shape_index": -1}
        else:
            shape_index = mi.Int32(-1)
            for shape in mi_scene.shapes():
                position = shape_names.index(shape.id())
                shape_index = dr.select(valid & (si.shape == mi.ShapePtr(shape)), position, shape_index)
        albedo = dr.select(valid, bsdf.eval_diffuse_reflectance(si, valid), 0.0)
        normal = dr.select(valid, si.sh_frame.n, 0.0)
        return {"depth": dr.select(valid, si.t, 0.0), "normal": normal, "albedo": albedo,
                "position": si.p, "shape_index": shape_index}

    def _motion(self, frame_index: int, traced: dict, jitter: tuple[float, float]) -> np.ndarray:
        """Position in frame t-1's (unjittered) image of each sample's surface point, minus the sample position."""
        s, scene = self.settings, self.scene
        previous = max(frame_index - 1, 0)
        shape_index, depth = traced["shape_index"], traced["depth"]
        points = np.where((depth > 0)[:, None], traced["position"],
                          traced["camera_origin"] + SKY_DISTANCE * traced["view_direction"]).astype(np.float64)
        previous_points = points.copy()
        for position, obj in enumerate(scene.objects):
            here = obj.transforms[frame_index]
            before = obj.transforms[previous]
            if np.array_equal(here, before):
                continue
            mask = shape_index == position
            previous_points[mask] = apply_to_points(before @ np.linalg.inv(here), points[mask])
        sky = depth <= 0
        if np.any(sky):
            # Directions at infinity move with the camera's rotation only, not with its translation.
            offset = np.asarray(scene.cameras[previous].origin) - np.asarray(scene.cameras[frame_index].origin)
            previous_points[sky] += offset
        image_position, in_front = scene.cameras[previous].project(previous_points, s.width, s.height)
        motion = image_position - traced["film_position"]
        # A point behind the previous camera has no previous image position: report no motion.
        motion[~in_front] = 0.0
        return motion.astype(np.float32)


def _negate(mask):
    """Logical not of a Dr.Jit mask or, in scalar variants, a Python bool (where ~True would be -2)."""
    return (not mask) if isinstance(mask, bool) else ~mask


def _mis_weight(dr, pdf_a, pdf_b):
    """Power heuristic a^2 / (a^2 + b^2), written as 1 / (1 + (b/a)^2).

    The textbook form overflows float32 for pdfs above ~1e19 (a light sampled at a grazing angle from a point
    next to it): inf / inf gives NaN. The ratio form stays finite and gives 1 or 0 at the extremes.
    """
    if isinstance(pdf_a, (int, float)):  # scalar variants: Python floats, where / 0 raises
        if not pdf_a > 0:
            return 0.0
        ratio = pdf_b / pdf_a
        weight = 1.0 / (1.0 + ratio * ratio)  # float * float overflows to inf (** would raise)
        return weight if math.isfinite(weight) else 0.0
    ratio = pdf_b / pdf_a
    weight = dr.rcp(dr.fma(ratio, ratio, 1.0))
    return dr.detach(dr.select((pdf_a > 0) & dr.isfinite(weight), weight, 0.0), True)


def _to_numpy(value) -> np.ndarray:
    array = np.asarray(value)
    if array.ndim == 2 and array.shape[0] in (2, 3) and array.shape[1] != array.shape[0]:
        array = array.T  # Dr.Jit vectors convert component-major: (3, N) -> (N, 3)
    return np.ascontiguousarray(array, dtype=np.float32) if array.dtype.kind == "f" else array
