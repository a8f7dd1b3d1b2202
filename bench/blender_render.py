"""Blender side of bench/localisation_scenes.py: unlit renders of an object with and without an added part.

Run by ``localisation_scenes.py`` as ``blender -b --python bench/blender_render.py -- JOB.json``; it is
not imported by anything else. The job names the object OBJ (with UVs and a texture, or one colour), the
part OBJ and its colour, and the cameras (NeRF-synthetic ``transform_matrix`` c2w, ``camera_angle_x``).
For each camera list it writes, under the job's output folder:

* ``<name>_edited_<i>.png``  RGBA, object + part, transparent background (the NeRF-synthetic layout);
* ``<name>_original_<i>.png`` RGBA, object alone (only where the job asks: the ring);
* ``<name>_cover_<i>.png``   RGB, part pure red, object pure green, background black: per-view coverage.

Shading is emission only (the albedo, unlit), colour management "Standard", so the PNGs hold the
texture's sRGB values as they are: the voxel grid has no view dependence, so lighting would only be
baked into it. Cycles on the CPU (Eevee needs an OpenGL context a headless server lacks).
"""

import json
import sys

import bpy


def srgb_to_linear(c):
    return c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4


def emission_material(name, colour=None, image_path=None):
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    nodes.clear()
    out = nodes.new("ShaderNodeOutputMaterial")
    emit = nodes.new("ShaderNodeEmission")
    links.new(emit.outputs["Emission"], out.inputs["Surface"])
    if image_path:
        tex = nodes.new("ShaderNodeTexImage")
        tex.image = bpy.data.images.load(image_path)
        tex.interpolation = "Linear"
        links.new(tex.outputs["Color"], emit.inputs["Color"])
    else:
        emit.inputs["Color"].default_value = (*[srgb_to_linear(c) for c in colour], 1.0)
    return mat


def import_obj(path, material):
    before = set(bpy.data.objects)
    bpy.ops.wm.obj_import(filepath=path, forward_axis="Y", up_axis="Z")  # files are written in Blender's frame
    (obj,) = set(bpy.data.objects) - before
    obj.data.materials.clear()
    obj.data.materials.append(material)
    return obj


def main():
    job = json.load(open(sys.argv[sys.argv.index("--") + 1]))
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.use_denoising = False
    scene.cycles.max_bounces = 0
    scene.render.resolution_x = scene.render.resolution_y = job["size"]
    scene.render.resolution_percentage = 100
    scene.render.film_transparent = True
    scene.render.image_settings.compression = 0
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.world = bpy.data.worlds.new("black")
    scene.world.color = (0.0, 0.0, 0.0)

    albedo = emission_material("albedo", job.get("object_colour"), job.get("object_texture"))
    part_colour = emission_material("part", job["part_colour"])
    red, green = emission_material("red", (1.0, 0.0, 0.0)), emission_material("green", (0.0, 1.0, 0.0))
    obj = import_obj(job["object_obj"], albedo)
    part = import_obj(job["part_obj"], part_colour)

    cam = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    scene.collection.objects.link(cam)
    scene.camera = cam
    cam.data.sensor_fit = "HORIZONTAL"
    cam.data.angle = job["camera_angle_x"]
    cam.data.clip_start, cam.data.clip_end = 0.1, 100.0

    def shoot(path, samples, transparent=True):
        scene.cycles.samples = samples
        scene.render.film_transparent = transparent
        scene.render.image_settings.color_mode = "RGBA" if transparent else "RGB"
        scene.render.filepath = path
        bpy.ops.render.render(write_still=True)

    for views in job["views"]:
        for i, c2w in enumerate(views["c2w"]):
            from mathutils import Matrix

            cam.matrix_world = Matrix(c2w)
            stem = f"{job['out']}/{views['name']}"
            obj.data.materials[0], part.data.materials[0] = albedo, part_colour
            part.hide_render = False
            shoot(f"{stem}_edited_{i:03d}.png", job["samples"])
            if views.get("original"):
                part.hide_render = True
                shoot(f"{stem}_original_{i:03d}.png", job["samples"])
                part.hide_render = False
            obj.data.materials[0], part.data.materials[0] = green, red
            shoot(f"{stem}_cover_{i:03d}.png", job["samples"], transparent=False)


main()
