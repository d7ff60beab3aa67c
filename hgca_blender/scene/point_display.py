"""How an imported scan is drawn: the Geometry Nodes group "hGCA Points" on each scan object.

Blender's Solid view colours only meshes by their colour attribute (Viewport Shading > Color > Attribute); a
Geometry Nodes point cloud is drawn in its material's solid colour there. So in the viewport each point becomes a
small tetrahedron (4 vertices, the lightest closed shape) that carries the scan's colour attribute, and renders
keep real round points (Cycles draws them as spheres). The group's "Render as Points" input turns the render
shapes into the viewport's ones, for a Workbench render that looks like Solid view.

The realized tetrahedra are joined after the scan's own mesh, so the result keeps that mesh's active colour
attribute (Join Geometry and Realize Instances take it from their first mesh): that is the one Solid view draws.
"""
from __future__ import annotations

import math

import bpy

ROLE_KEY = "hgca_role"  # custom property marking what the add-on created: "scan", "region", "result", "points"
POINT_NODE_GROUP = "hGCA Points"
RADIUS_INPUT = "Radius"
RENDER_POINTS_INPUT = "Render as Points"
DEFAULT_RADIUS = 0.03
GROUP_VERSION = 2  # 1: Mesh to Points only (Solid view grey); 2: tetrahedra in the viewport


def _new_group() -> bpy.types.NodeTree:
    ng = bpy.data.node_groups.new(POINT_NODE_GROUP, "GeometryNodeTree")
    ng[ROLE_KEY] = "points"
    ng["hgca_version"] = GROUP_VERSION
    ng.interface.new_socket(name="Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    radius = ng.interface.new_socket(name=RADIUS_INPUT, in_out="INPUT", socket_type="NodeSocketFloat")
    radius.default_value, radius.min_value = DEFAULT_RADIUS, 0.0
    as_points = ng.interface.new_socket(name=RENDER_POINTS_INPUT, in_out="INPUT", socket_type="NodeSocketBool")
    as_points.default_value = True
    ng.interface.new_socket(name="Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    return ng


def _link_group(ng: bpy.types.NodeTree) -> None:
    nodes, links = ng.nodes, ng.links
    node_in, node_out = nodes.new("NodeGroupInput"), nodes.new("NodeGroupOutput")
    to_points = nodes.new("GeometryNodeMeshToPoints")
    links.new(node_in.outputs[0], to_points.inputs["Mesh"])
    links.new(node_in.outputs[RADIUS_INPUT], to_points.inputs["Radius"])

    # a regular tetrahedron around each point: a 3-sided cone, circumradius = Radius
    cone = nodes.new("GeometryNodeMeshCone")
    cone.inputs["Vertices"].default_value = 3
    cone.inputs["Radius Top"].default_value = 0.0
    base = nodes.new("ShaderNodeMath")
    base.operation, base.inputs[1].default_value = "MULTIPLY", math.sqrt(8.0) / 3.0
    depth = nodes.new("ShaderNodeMath")
    depth.operation, depth.inputs[1].default_value = "MULTIPLY", 4.0 / 3.0
    links.new(node_in.outputs[RADIUS_INPUT], base.inputs[0])
    links.new(node_in.outputs[RADIUS_INPUT], depth.inputs[0])
    links.new(base.outputs[0], cone.inputs["Radius Bottom"])
    links.new(depth.outputs[0], cone.inputs["Depth"])
    instance = nodes.new("GeometryNodeInstanceOnPoints")
    links.new(node_in.outputs[0], instance.inputs["Points"])
    links.new(cone.outputs["Mesh"], instance.inputs["Instance"])
    realize = nodes.new("GeometryNodeRealizeInstances")
    links.new(instance.outputs["Instances"], realize.inputs[0])
    join = nodes.new("GeometryNodeJoinGeometry")
    # a multi-input socket lists its newest link first: link the shapes, then the scan's mesh, so the mesh leads
    links.new(realize.outputs[0], join.inputs[0])
    links.new(node_in.outputs[0], join.inputs[0])

    viewport = nodes.new("GeometryNodeIsViewport")
    use_points = nodes.new("FunctionNodeBooleanMath")
    use_points.operation = "NIMPLY"  # round points: a render (not the viewport) that asks for them
    links.new(node_in.outputs[RENDER_POINTS_INPUT], use_points.inputs[0])
    links.new(viewport.outputs[0], use_points.inputs[1])
    switch = nodes.new("GeometryNodeSwitch")
    switch.input_type = "GEOMETRY"
    links.new(use_points.outputs[0], switch.inputs["Switch"])
    links.new(join.outputs[0], switch.inputs["False"])
    links.new(to_points.outputs["Points"], switch.inputs["True"])
    links.new(switch.outputs[0], node_out.inputs[0])
    for x, node in enumerate((node_in, cone, instance, realize, join, switch, node_out)):
        node.location = (x * 220 - 700, 0)


def point_display_group(created) -> bpy.types.NodeTree:
    """The shared "hGCA Points" group (made once per file, appended to `created.node_groups` when new); its
    "Radius" input is set per object on the modifier, so each scan keeps its own point size."""
    existing = bpy.data.node_groups.get(POINT_NODE_GROUP)
    if (existing is not None and existing.get(ROLE_KEY) == "points" and existing.bl_idname == "GeometryNodeTree"
            and existing.get("hgca_version") == GROUP_VERSION):
        return existing
    ng = _new_group()
    created.node_groups.append(ng)
    _link_group(ng)
    return ng


def _points_input(obj: bpy.types.Object, name: str):
    """(modifier, socket identifier) of the "hGCA Points" modifier's input `name`, or None."""
    for mod in obj.modifiers:
        if mod.type == "NODES" and mod.node_group is not None and mod.node_group.get(ROLE_KEY) == "points":
            item = mod.node_group.interface.items_tree.get(name)
            if item is not None:
                return mod, item.identifier
    return None


def _set_input(obj: bpy.types.Object, name: str, value: float | bool) -> bool:
    found = _points_input(obj, name)
    if found is None:
        return False
    mod, key = found
    mod[key] = value
    obj.update_tag()
    return True


def set_point_radius(obj: bpy.types.Object, radius: float) -> bool:
    """Set the point size of a scan shown by the "hGCA Points" modifier; False when it has none."""
    return _set_input(obj, RADIUS_INPUT, float(radius))


def point_radius(obj: bpy.types.Object) -> float | None:
    found = _points_input(obj, RADIUS_INPUT)
    return None if found is None else float(found[0][found[1]])


def set_render_points(obj: bpy.types.Object, as_points: bool) -> bool:
    """Renders draw round points (True) or the viewport's coloured shapes (False); False when not a scan."""
    return _set_input(obj, RENDER_POINTS_INPUT, bool(as_points))
