"""Shader node materials of the generated scenes (bpy is passed in; imported only by the caller)."""
from __future__ import annotations

import numpy as np

from .layout import BLOCK, ROAD


def enable_nodes(idblock) -> None:
    """Give a material/world its node tree (Blender 5 always has one; use_nodes is deprecated)."""
    if idblock.node_tree is None:
        idblock.use_nodes = True


class Nodes:
    """Small helper to build shader node graphs by name."""

    def __init__(self, mat):
        enable_nodes(mat)
        self.nt = mat.node_tree
        self.nt.nodes.clear()

    def n(self, kind: str, **props):
        node = self.nt.nodes.new(kind)
        for k, v in props.items():
            if k in node.inputs:
                node.inputs[k].default_value = v
            else:
                setattr(node, k, v)
        return node

    def link(self, a, b) -> None:
        self.nt.links.new(a, b)

    def math(self, op: str, a, b=None, **kw):
        m = self.n("ShaderNodeMath", operation=op, **kw)
        for i, x in enumerate((a, b)):
            if x is None:
                continue
            if isinstance(x, (int, float)):
                m.inputs[i].default_value = x
            else:
                self.link(x, m.inputs[i])
        return m.outputs[0]

    def mix(self, fac, c1, c2, blend: str = "MIX"):
        m = self.n("ShaderNodeMix", data_type="RGBA", blend_type=blend)
        for sock, x in ((m.inputs[0], fac), (m.inputs[6], c1), (m.inputs[7], c2)):
            if isinstance(x, (int, float)):
                sock.default_value = x
            elif isinstance(x, (tuple, list)):
                sock.default_value = (*x[:3], 1.0)
            else:
                self.link(x, sock)
        return m.outputs[2]

    def mul(self, color, factor):
        """``color * factor`` for a scalar or colour factor (no clamping)."""
        return self.mix(1.0, color, factor, "MULTIPLY")

    def output(self, color) -> None:
        bsdf = self.n("ShaderNodeBsdfDiffuse")
        bsdf.inputs["Roughness"].default_value = 0.5
        self.link(color, bsdf.inputs["Color"])
        out = self.n("ShaderNodeOutputMaterial")
        self.link(bsdf.outputs[0], out.inputs["Surface"])


def _coords(g: Nodes, offset: np.ndarray):
    """Object (= world, identity transforms) coordinates shifted by a seed offset."""
    tc = g.n("ShaderNodeTexCoord")
    mp = g.n("ShaderNodeMapping")
    mp.inputs["Location"].default_value = tuple(offset)
    g.link(tc.outputs["Object"], mp.inputs["Vector"])
    return tc.outputs["Object"], mp.outputs[0]


def _detail(g: Nodes, vec, scale: float, lo: float, hi: float, roughness: float = 0.6):
    """Multi-octave noise mapped to [lo, hi]: fine texture for feature matching."""
    nz = g.n("ShaderNodeTexNoise", noise_dimensions="3D")
    nz.inputs["Scale"].default_value = scale
    nz.inputs["Detail"].default_value = 5.0  # octaves: finer ones cost render time for little texture
    nz.inputs["Roughness"].default_value = roughness
    g.link(vec, nz.inputs["Vector"])
    return _remap(g, nz.outputs["Fac"], 0.2, 0.8, lo, hi)


def _remap(g: Nodes, x, a: float, b: float, lo: float, hi: float):
    m = g.n("ShaderNodeMapRange", clamp=True)
    m.inputs["From Min"].default_value = a
    m.inputs["From Max"].default_value = b
    m.inputs["To Min"].default_value = lo
    m.inputs["To Max"].default_value = hi
    g.link(x, m.inputs["Value"])
    return m.outputs["Result"]


def _attr(g: Nodes, name: str):
    return g.n("ShaderNodeAttribute", attribute_name=name).outputs["Color"]


def mat_objects(bpy, offset: np.ndarray, windows: bool):
    """Vertex-coloured objects: facades with window grids (walls) and noisy roofs."""
    mat = bpy.data.materials.new("objects_win" if windows else "objects")
    g = Nodes(mat)
    obj, vec = _coords(g, offset)
    wall, roof = _attr(g, "col"), _attr(g, "col2")
    col_wall = g.mul(wall, _detail(g, vec, 0.35, 0.8, 1.15))
    if windows:
        # Window grid on vertical walls: bricks in (x + y, z), one row per storey.
        sep = g.n("ShaderNodeSeparateXYZ")
        g.link(obj, sep.inputs[0])
        comb = g.n("ShaderNodeCombineXYZ")
        g.link(g.math("ADD", sep.outputs[0], sep.outputs[1]), comb.inputs[0])
        g.link(sep.outputs[2], comb.inputs[1])
        br = g.n("ShaderNodeTexBrick", offset=0.0, squash=1.0)
        for k, v in (("Scale", 1.0), ("Mortar Size", 0.9), ("Brick Width", 3.0), ("Row Height", 3.3),
                     ("Mortar Smooth", 0.0)):
            br.inputs[k].default_value = v
        g.link(comb.outputs[0], br.inputs["Vector"])
        glass = g.mul((0.08, 0.1, 0.14), _detail(g, vec, 2.0, 0.5, 1.6))
        col_wall = g.mix(br.outputs["Fac"], glass, col_wall)
    vor = g.n("ShaderNodeTexVoronoi")
    vor.inputs["Scale"].default_value = 0.6
    g.link(vec, vor.inputs["Vector"])
    speck = _remap(g, vor.outputs["Distance"], 0.0, 0.5, 0.7, 1.1)
    col_roof = g.mul(roof, speck)
    col_roof = g.mul(col_roof, _detail(g, vec, 0.8, 0.8, 1.1))
    geo = g.n("ShaderNodeNewGeometry")
    sep_n = g.n("ShaderNodeSeparateXYZ")
    g.link(geo.outputs["Normal"], sep_n.inputs[0])
    is_roof = g.math("GREATER_THAN", sep_n.outputs[2], 0.5)
    g.output(g.mix(is_roof, col_wall, col_roof))
    return mat


def _cell_colour(g: Nodes, obj, px: float, py: float, palette: list, offset: np.ndarray):
    """A colour per grid cell of size (px, py) chosen from ``palette`` by a hashed cell id."""
    sep = g.n("ShaderNodeSeparateXYZ")
    g.link(obj, sep.inputs[0])
    comb = g.n("ShaderNodeCombineXYZ")
    g.link(g.math("FLOOR", g.math("DIVIDE", sep.outputs[0], px)), comb.inputs[0])
    g.link(g.math("FLOOR", g.math("DIVIDE", sep.outputs[1], py)), comb.inputs[1])
    comb.inputs[2].default_value = float(offset[2])
    wn = g.n("ShaderNodeTexWhiteNoise", noise_dimensions="3D")
    g.link(comb.outputs[0], wn.inputs["Vector"])
    ramp = g.n("ShaderNodeValToRGB")
    cr = ramp.color_ramp
    cr.interpolation = "CONSTANT"
    while len(cr.elements) < len(palette):
        cr.elements.new(0.5)
    for i, c in enumerate(palette):
        cr.elements[i].position = i / len(palette)
        cr.elements[i].color = (*c, 1.0)
    g.link(wn.outputs["Value"], ramp.inputs["Fac"])
    return ramp.outputs["Color"], sep


def mat_ground(bpy, offset: np.ndarray, kind: str):
    """Ground: city blocks with roads, or village fields with dirt tracks."""
    mat = bpy.data.materials.new("ground")
    g = Nodes(mat)
    obj, vec = _coords(g, offset)
    if kind == "village":
        pal = [(0.2, 0.32, 0.1), (0.35, 0.4, 0.15), (0.55, 0.5, 0.25), (0.4, 0.3, 0.18), (0.25, 0.38, 0.12),
               (0.5, 0.45, 0.3)]
        cell, sep = _cell_colour(g, obj, 45.0, 30.0, pal, offset)
        per, road_w, road_c = (45.0, 30.0), 2.5, (0.45, 0.38, 0.28)
    else:
        pal = [(0.3, 0.3, 0.3), (0.4, 0.38, 0.35), (0.2, 0.3, 0.12), (0.35, 0.33, 0.3), (0.25, 0.25, 0.27),
               (0.45, 0.42, 0.38)]
        cell, sep = _cell_colour(g, obj, BLOCK, BLOCK, pal, offset)
        per, road_w, road_c = (BLOCK, BLOCK), ROAD, (0.1, 0.1, 0.11)
    road = None
    for ax, p in zip((0, 1), per):
        m = g.math("LESS_THAN", g.math("FRACT", g.math("DIVIDE", sep.outputs[ax], p)), road_w / p)
        road = m if road is None else g.math("MAXIMUM", road, m)
    vor = g.n("ShaderNodeTexVoronoi")
    vor.inputs["Scale"].default_value = 0.35
    g.link(vec, vor.inputs["Vector"])
    lots = g.mul(cell, _remap(g, vor.outputs["Distance"], 0.0, 0.6, 0.65, 1.15))
    lots = g.mul(lots, _detail(g, vec, 0.08, 0.7, 1.2))
    roads = g.mul(road_c, _detail(g, vec, 0.5, 0.7, 1.3))
    g.output(g.mix(road, lots, roads))
    return mat


def mat_terrain(bpy, offset: np.ndarray):
    """Terrain coloured by height and slope, with multi-scale noise."""
    mat = bpy.data.materials.new("terrain")
    g = Nodes(mat)
    obj, vec = _coords(g, offset)
    sep = g.n("ShaderNodeSeparateXYZ")
    g.link(obj, sep.inputs[0])
    hnoise = g.math("ADD", sep.outputs[2], g.math("MULTIPLY", _detail(g, vec, 0.03, -1, 1), 15.0))
    ramp = g.n("ShaderNodeValToRGB")
    cr = ramp.color_ramp
    stops = [(0.0, (0.2, 0.3, 0.1)), (0.3, (0.12, 0.22, 0.08)), (0.55, (0.35, 0.3, 0.2)),
             (0.8, (0.45, 0.43, 0.4)), (0.95, (0.85, 0.85, 0.88))]
    while len(cr.elements) < len(stops):
        cr.elements.new(0.5)
    for e, (p, c) in zip(cr.elements, stops):
        e.position, e.color = p, (*c, 1.0)
    g.link(g.math("DIVIDE", hnoise, 160.0), ramp.inputs["Fac"])
    geo = g.n("ShaderNodeNewGeometry")
    sn = g.n("ShaderNodeSeparateXYZ")
    g.link(geo.outputs["Normal"], sn.inputs[0])
    rock = _remap(g, sn.outputs[2], 0.7, 0.85, 1.0, 0.0)
    col = g.mix(rock, ramp.outputs["Color"], (0.4, 0.37, 0.33))
    vor = g.n("ShaderNodeTexVoronoi")
    vor.inputs["Scale"].default_value = 0.3
    g.link(vec, vor.inputs["Vector"])
    col = g.mul(col, _remap(g, vor.outputs["Distance"], 0.0, 0.6, 0.6, 1.15))
    g.output(g.mul(col, _detail(g, vec, 0.15, 0.7, 1.25)))
    return mat
