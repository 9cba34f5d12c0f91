"""Compositor set-up for the add-on's results, for every supported Blender.

Blender 5.0 replaced the scene's own compositor tree: the compositor is a
``CompositorNodeTree`` node group assigned to ``scene.compositing_node_group``
and its Group Output node (with an ``Image`` output socket declared on the
group interface) replaces the Composite node. Blender 4.2-4.5 use
``scene.use_nodes = True`` and ``scene.node_tree`` with a Composite node.

:func:`compositor_api` picks the variant from ``bpy.app.version`` and
:func:`compositor_plan` lays out the nodes and links; the add-on applies the
plan with bpy. Both are plain data so the 4.x branch is tested without a 4.x
Blender.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

OUTPUT_NODE = "DIBR-GS Output"
VIEWER_NODE = "DIBR-GS Viewer"
IMAGE_NODE_PREFIX = "DIBR-GS Image "


@dataclass(frozen=True)
class CompositorAPI:
    """How a Blender version exposes the compositor.

    Attributes:
        node_group: True for 5.0+ (``scene.compositing_node_group``), False
            for 4.2-4.5 (``scene.use_nodes`` + ``scene.node_tree``).
        output_node_type: bl_idname of the final output node.
        output_socket: name of its image input socket.
        viewer_node_type: bl_idname of the Viewer node.
        image_node_type: bl_idname of the Image node.
    """

    node_group: bool
    output_node_type: str
    output_socket: str = "Image"
    viewer_node_type: str = "CompositorNodeViewer"
    image_node_type: str = "CompositorNodeImage"


def compositor_api(version: Sequence[int]) -> CompositorAPI:
    """The compositor API of Blender ``version`` (``bpy.app.version``); 4.2 or later."""
    v = tuple(int(x) for x in version[:2])
    if v < (4, 2):
        raise ValueError(f"Blender {'.'.join(map(str, version))} is older than 4.2, which the add-on needs")
    if v >= (5, 0):
        return CompositorAPI(node_group=True, output_node_type="NodeGroupOutput")
    return CompositorAPI(node_group=False, output_node_type="CompositorNodeComposite")


@dataclass
class CompositorPlan:
    """Nodes and links that show result images.

    ``image_nodes`` maps node name -> (image datablock name, (x, y) location);
    ``links`` are (from node, from socket, to node, to socket) tuples.
    """

    api: CompositorAPI
    image_nodes: dict[str, tuple[str, tuple[float, float]]] = field(default_factory=dict)
    output: tuple[str, tuple[float, float]] = (OUTPUT_NODE, (400.0, 0.0))
    viewer: tuple[str, tuple[float, float]] = (VIEWER_NODE, (400.0, -200.0))
    links: list[tuple[str, str, str, str]] = field(default_factory=list)


def image_node_name(image_name: str) -> str:
    return IMAGE_NODE_PREFIX + image_name


def compositor_plan(images: Sequence[str], selected: str | None, api: CompositorAPI) -> CompositorPlan:
    """One Image node per image in a column, the selected one wired to output and Viewer.

    ``selected`` defaults to the first image; it must be one of ``images``.
    """
    images = list(dict.fromkeys(images))
    if not images:
        raise ValueError("no result images to show")
    if selected is None:
        selected = images[0]
    if selected not in images:
        raise ValueError(f"{selected!r} is not among the result images")
    plan = CompositorPlan(api=api)
    for i, name in enumerate(images):
        plan.image_nodes[image_node_name(name)] = (name, (0.0, -300.0 * i))
    src = image_node_name(selected)
    plan.links = [(src, "Image", plan.output[0], api.output_socket),
                  (src, "Image", plan.viewer[0], "Image")]
    return plan
