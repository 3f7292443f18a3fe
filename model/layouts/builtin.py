"""The built-in layouts, written in the layout file format (``model.layouts.layout``).

- ``denoiser``: the frame bundle itself (``model.io.frames``): channels ``<buffer>.<component>``, reference parts
  ``reference_x{s}``, the 'jitter' attribute.
- ``blender-cycles``: a multilayer EXR as Blender writes it from Cycles, channels ``ViewLayer.<Pass>.<component>``:
  Blender 5 (one part per pass; ``Diffuse Color``, ``Glossy Color``) and Blender 4.x (one part; the same passes
  named ``DiffCol``, ``GlossCol``). Conventions measured on Cycles output (tests/model/layouts/
  test_blender_cycles.py proves each on the committed fixtures of both): ``Vector.X/Y`` is the offset to the previous
  frame's position in pixels with y up (``Vector.Z/W`` looks at the next frame: unused); ``Depth.Z`` is planar
  (along the view axis), 1e10 where nothing is hit; ``Normal`` is world space; with a 0.01 px pixel filter the
  one sample sits at the pixel centre, unless the note carries ``jitter=X,Y`` (``scripts/render_blender.py
  --jitter halton`` shifts the camera by that many pixels, x right and y down, per frame; the Vector pass is then
  still the frame bundle's motion, since Cycles leaves the shift out of it: proved on a second fixture).
  Guides are the first-hit passes Diffuse Color and Glossy Color: Cycles'
  Denoising Albedo / Denoising Normal follow glossy bounces, so they are noisy at 1 spp.
  Planar depth needs the vertical field of view: ``scripts/render_blender.py`` stamps it into the header as
  Blender's metadata note ``fov_y_degrees=...``; else give it to the import (``--fov-y``).
- ``generic``: R, G, B for the colour and the frame bundle's names (or N and Z) for the AOVs, in
  the frame bundle's conventions; a 'jitter' attribute if present, else the pixel centre.
"""

from __future__ import annotations

from model.io.frames import BUFFERS
from model.layouts.layout import Layout, parse_layout


def _own_names(buffer: str) -> list[str]:
    return list(BUFFERS[buffer].channels)


def _blender_pass(name: str) -> list[str]:
    return [f"ViewLayer.{name}.{component}" for component in "RGB"]


DENOISER = {
    "name": "denoiser",
    "description": "the frame bundle: <buffer>.<component> channels, reference_x<s> parts, 'jitter' attribute",
    "channels": {buffer: _own_names(buffer) for buffer in BUFFERS},
    "sample": {"jitter": "header"},
}

BLENDER_CYCLES = {
    "name": "blender-cycles",
    "description": "Blender 5 or 4.x multilayer EXR from Cycles (view layer 'ViewLayer'), default pass names",
    "hint": "in Blender, enable the passes Combined, Z, Normal, Vector and Diffuse Color (View Layer Properties > "
            "Passes; Vector needs motion blur off) and save as OpenEXR MultiLayer, as scripts/render_blender.py does; "
            "Blender 5 names them Combined, Depth, Normal, Vector, Diffuse Color and Glossy Color, Blender 4.x "
            "Combined, Depth, Normal, Vector, DiffCol and GlossCol (either is read)",
    "channels": {
        "color": ["ViewLayer.Combined.R", "ViewLayer.Combined.G", "ViewLayer.Combined.B"],
        # Blender 5's pass names first, then Blender 4.x's (DNA_scene_enums.h before 5.0: DiffCol, GlossCol).
        "albedo": [_blender_pass("Diffuse Color"), _blender_pass("DiffCol")],
        "specular_albedo": [_blender_pass("Glossy Color"), _blender_pass("GlossCol")],
        "normal": ["ViewLayer.Normal.X", "ViewLayer.Normal.Y", "ViewLayer.Normal.Z"],
        "depth": ["ViewLayer.Depth.Z"],
        "motion": ["ViewLayer.Vector.X", "ViewLayer.Vector.Y"],
    },
    "motion": {"points_to": "previous", "units": "pixels", "y": "up"},
    "depth": {"kind": "planar", "no_hit_at_or_above": 1e9, "fov_y_attribute": "Note"},
    "normal": {"space": "world"},
    # scripts/render_blender.py --jitter halton stamps the jitter into the note ("... jitter=X,Y"); without it the
    # sample is at the pixel centre (a 0.01 px pixel filter).
    "sample": {"jitter": "header-or-centre", "jitter_attribute": "Note", "frame_index_attribute": "Frame"},
    # Alpha, and the Vector pass's motion towards the next frame.
    "ignore": ["ViewLayer.Combined.A", "ViewLayer.Vector.Z", "ViewLayer.Vector.W"],
}

GENERIC = {
    "name": "generic",
    "description": "R G B colour plus AOVs named as in the frame bundle (or N, Z), in its conventions",
    "channels": {
        "color": [["R", "G", "B"], _own_names("color")],
        "albedo": _own_names("albedo"),
        "normal": [_own_names("normal"), ["N.X", "N.Y", "N.Z"], ["N.R", "N.G", "N.B"]],
        "depth": [_own_names("depth"), ["Z"], ["depth.R"]],
        "motion": [_own_names("motion"), ["motion.R", "motion.G"]],
        **{buffer: _own_names(buffer) for buffer in ("specular_albedo", "diffuse", "specular", "roughness",
                                                      "reference", "reference_albedo", "reference_specular_albedo")},
    },
    "sample": {"jitter": "header-or-centre"},
    "ignore": ["A"],
}

BUILTIN_LAYOUTS: dict[str, Layout] = {
    content["name"]: parse_layout(content, f"built-in {content['name']!r}")
    for content in (DENOISER, BLENDER_CYCLES, GENERIC)
}
