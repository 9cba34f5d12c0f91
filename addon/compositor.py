"""Result images in the compositor, for Blender 4.2-4.5 and 5.0+.

The node layout comes from ``dibrgs_core.bridge.compositor`` (tested without
Blender); this module applies it: Image nodes for every result, the
selected one wired to the output (Group Output on 5.0+, Composite on 4.x)
and to a Viewer node. :func:`select` rewires to another result.
"""
from __future__ import annotations

import bpy

from ._core import compositor as plan_mod

TREE_NAME = "DIBR-GS Results"


def _tree(scene: bpy.types.Scene, api) -> bpy.types.NodeTree:
    if api.node_group:  # Blender 5.0+: a node group assigned to the scene
        tree = scene.compositing_node_group
        if tree is None:
            tree = bpy.data.node_groups.new(TREE_NAME, "CompositorNodeTree")
            scene.compositing_node_group = tree
        if not any(s.in_out == "OUTPUT" and s.name == api.output_socket for s in tree.interface.items_tree
                   if s.item_type == "SOCKET"):
            tree.interface.new_socket(api.output_socket, in_out="OUTPUT", socket_type="NodeSocketColor")
        return tree
    scene.use_nodes = True  # Blender 4.2-4.5: the scene's own tree
    return scene.node_tree


def _node(tree, name: str, bl_idname: str, location) -> bpy.types.Node:
    node = tree.nodes.get(name)
    if node is None or node.bl_idname != bl_idname:
        if node is not None:
            tree.nodes.remove(node)
        node = tree.nodes.new(bl_idname)
        node.name = node.label = name
    node.location = location
    return node


def show(scene: bpy.types.Scene, image_names: list[str], selected: str | None = None) -> bpy.types.NodeTree:
    """Image nodes for ``image_names`` (bpy image datablock names); ``selected`` wired to the outputs."""
    api = plan_mod.compositor_api(bpy.app.version)
    plan = plan_mod.compositor_plan(image_names, selected, api)
    tree = _tree(scene, api)
    for node in list(tree.nodes):  # drop image nodes of results that are gone
        if node.name.startswith(plan_mod.IMAGE_NODE_PREFIX) and node.name not in plan.image_nodes:
            tree.nodes.remove(node)
    for node_name, (image_name, loc) in plan.image_nodes.items():
        node = _node(tree, node_name, api.image_node_type, loc)
        img = bpy.data.images[image_name]
        node.image = img
        if img.source == "SEQUENCE":
            node.frame_duration = int(img.get("dibrgs_frames", 1))
            node.frame_start = 1
    _node(tree, plan.output[0], api.output_node_type, plan.output[1])
    _node(tree, plan.viewer[0], api.viewer_node_type, plan.viewer[1])
    _link(tree, plan)
    return tree


def _link(tree, plan) -> None:
    out, viewer = tree.nodes[plan.output[0]], tree.nodes[plan.viewer[0]]
    for link in list(tree.links):
        if link.to_node in (out, viewer):
            tree.links.remove(link)
    for src, src_sock, dst, dst_sock in plan.links:
        tree.links.new(tree.nodes[src].outputs[src_sock], tree.nodes[dst].inputs[dst_sock])


def select(scene: bpy.types.Scene, image_name: str) -> None:
    """Wire the result ``image_name`` to the output and the Viewer."""
    api = plan_mod.compositor_api(bpy.app.version)
    names = [r.name for r in scene.dibrgs.results]
    plan = plan_mod.compositor_plan(names, image_name, api)
    tree = _tree(scene, api)
    if any(n not in tree.nodes for n in plan.image_nodes):
        show(scene, names, image_name)
        return
    _link(tree, plan)


def wired_image(scene: bpy.types.Scene) -> str | None:
    """Name of the image currently wired to the compositor output (None if none)."""
    api = plan_mod.compositor_api(bpy.app.version)
    tree = scene.compositing_node_group if api.node_group else scene.node_tree
    if tree is None or plan_mod.OUTPUT_NODE not in tree.nodes:
        return None
    sock = tree.nodes[plan_mod.OUTPUT_NODE].inputs[api.output_socket]
    if not sock.links:
        return None
    node = sock.links[0].from_node
    return node.image.name if getattr(node, "image", None) else None
