"""Result images in the compositor, for Blender 4.2-4.5 and 5.0+.

The node layout comes from ``dibrgs_core.bridge.compositor`` (tested without
Blender); this module applies it: Image nodes for every result, the
selected one wired to the output the render actually uses and to a Viewer.

* Blender 5.0+: the scene's compositing node group (a new one when the scene
  has none). The render takes the first colour input of the *active* Group
  Output, so the result goes there; an existing tree (Render Layers -> Group
  Output) keeps its nodes and its active output is rewired, no second output
  is added.
* Blender 4.2-4.5: ``scene.use_nodes`` and ``scene.node_tree``; the result is
  wired to every Composite node (the render uses the active one, which the
  API does not expose), one is added when there is none.

Colour: result PNGs are sRGB, which the compositor decodes to linear; the
scene's view transform is set to Standard (look None, exposure 0, gamma 1,
no curves) so the render encodes them back to the same sRGB values (within
1/255: the render's dither). AgX, Blender's default, would shift their tones.

Running :func:`show` again with the same results changes nothing.
"""
from __future__ import annotations

import bpy

from ._core import compositor as plan_mod

TREE_NAME = "DIBR-GS Results"


def _api():
    return plan_mod.compositor_api(bpy.app.version)


def _tree(scene: bpy.types.Scene, api, create: bool = True) -> bpy.types.NodeTree | None:
    if api.node_group:  # Blender 5.0+: a node group assigned to the scene
        tree = scene.compositing_node_group
        if tree is None and create:
            tree = bpy.data.node_groups.new(TREE_NAME, "CompositorNodeTree")
            scene.compositing_node_group = tree
        return tree
    if create and not scene.use_nodes:  # Blender 4.2-4.5: the scene's own tree
        fresh = scene.node_tree is None
        scene.use_nodes = True
        if fresh:  # Blender's default tree: keep its Composite, drop Render Layers (no scene render needed)
            for node in list(scene.node_tree.nodes):
                if node.bl_idname == "CompositorNodeRLayers":
                    scene.node_tree.nodes.remove(node)
    return scene.node_tree


def _image_socket_5x(tree) -> str:
    """Identifier of the group's first colour output (the render result), created if there is none."""
    for item in tree.interface.items_tree:
        if item.item_type == "SOCKET" and item.in_out == "OUTPUT" and item.socket_type == "NodeSocketColor":
            return item.identifier
    return tree.interface.new_socket("Image", in_out="OUTPUT", socket_type="NodeSocketColor").identifier


def output_sockets(tree, api, create: bool = True) -> list:
    """The input sockets whose image the render uses (see the module docstring)."""
    if api.node_group:
        outs = [n for n in tree.nodes if n.bl_idname == api.output_node_type]
        active = next((n for n in outs if n.is_active_output), None)
        if active is None and outs:
            active = outs[0]
            if create:
                active.is_active_output = True
        if active is None:
            if not create:
                return []
            active = _node(tree, plan_mod.OUTPUT_NODE, api.output_node_type, (400.0, 0.0))
            active.is_active_output = True
        ident = _image_socket_5x(tree) if create else next(
            (i.identifier for i in tree.interface.items_tree if i.item_type == "SOCKET" and i.in_out == "OUTPUT"
             and i.socket_type == "NodeSocketColor"), None)
        return [s for s in active.inputs if s.identifier == ident]
    outs = [n for n in tree.nodes if n.bl_idname == api.output_node_type]
    if not outs and create:
        outs = [_node(tree, plan_mod.OUTPUT_NODE, api.output_node_type, (400.0, 0.0))]
    return [n.inputs[api.output_socket] for n in outs]


def _node(tree, name: str, bl_idname: str, location) -> bpy.types.Node:
    node = tree.nodes.get(name)
    if node is None or node.bl_idname != bl_idname:
        if node is not None:
            tree.nodes.remove(node)
        node = tree.nodes.new(bl_idname)
        node.name = node.label = name
        node.location = location
    return node


def color_manage(scene: bpy.types.Scene) -> None:
    """View settings under which the render reproduces the sRGB result images."""
    vs = scene.view_settings
    vs.view_transform = "Standard"
    vs.look = "None"
    vs.exposure, vs.gamma = 0.0, 1.0
    vs.use_curve_mapping = False
    scene.display_settings.display_device = "sRGB"


def show(scene: bpy.types.Scene, image_names: list[str], selected: str | None = None) -> bpy.types.NodeTree:
    """Image nodes for ``image_names`` (bpy image datablock names); ``selected`` wired to the outputs."""
    api = _api()
    plan = plan_mod.compositor_plan(image_names, selected, api)
    tree = _tree(scene, api)
    for node in list(tree.nodes):  # drop image nodes of results that are gone
        if node.name.startswith(plan_mod.IMAGE_NODE_PREFIX) and node.name not in plan.image_nodes:
            tree.nodes.remove(node)
    for node_name, (image_name, loc) in plan.image_nodes.items():
        node = _node(tree, node_name, api.image_node_type, loc)
        img = bpy.data.images[image_name]
        if node.image != img:
            node.image = img
        if img.source == "SEQUENCE":
            node.frame_duration = int(img.get("dibrgs_frames", 1))
            node.frame_start = 1
    _node(tree, plan.viewer[0], api.viewer_node_type, plan.viewer[1])
    _link(tree, plan, api)
    color_manage(scene)
    return tree


def _link(tree, plan, api) -> None:
    src = tree.nodes[plan.links[0][0]].outputs["Image"]
    targets = output_sockets(tree, api) + [tree.nodes[plan.viewer[0]].inputs["Image"]]
    for sock in targets:
        if sock.links and sock.links[0].from_socket == src:
            continue  # already wired: leave the tree as it is
        for link in list(sock.links):
            tree.links.remove(link)
        tree.links.new(src, sock)


def select(scene: bpy.types.Scene, image_name: str) -> None:
    """Wire the result ``image_name`` to the output and the Viewer."""
    api = _api()
    names = [r.name for r in scene.dibrgs.results]
    plan = plan_mod.compositor_plan(names, image_name, api)
    tree = _tree(scene, api)
    if any(n not in tree.nodes for n in plan.image_nodes):
        show(scene, names, image_name)
        return
    _link(tree, plan, api)


def wired_images(scene: bpy.types.Scene) -> list[str | None]:
    """Per output the render may use (see :func:`output_sockets`), the image wired to it (None if none)."""
    api = _api()
    tree = _tree(scene, api, create=False)
    if tree is None:
        return []
    out = []
    for sock in output_sockets(tree, api, create=False):
        node = sock.links[0].from_node if sock.links else None
        out.append(node.image.name if node is not None and getattr(node, "image", None) else None)
    return out


def wired_image(scene: bpy.types.Scene) -> str | None:
    """The image the render shows: wired to every output it may use, else None."""
    names = set(wired_images(scene))
    return names.pop() if len(names) == 1 else None
