"""Renders colf-synth scenes with Blender's Cycles (CPU), for `colf-synth --engine blender`.

Run by colf-synth (which embeds this file), not by hand:

    blender -b --factory-startup --threads 1 --python blender_clevr.py -- JOB.json

JOB.json lists scenes whose layout colf-synth sampled (objects, lights, cameras) and the PNG
files to write for each view: the colour image (Cycles path tracing, a fixed seed, a fixed
number of samples, no denoising, no adaptive sampling) and an object-id image (a second pass
in which every object emits a flat grey level of its own, one sample per pixel at the pixel
centre, no lights, no bounces, no dithering, the "Standard" view transform), which
colf-synth decodes into the mask. A scene's `extra_scenes` (uORF's scene manipulation) are
rendered after it, each with its own objects and lights and the scene's cameras. After each scene it prints `colf-scene-done INDEX` on
stdout. The scene follows the CLEVR recipe: CLEVR shapes with a matte "rubber" material on a
large grey floor, three area lights (key, fill, back). For the room presets an object may
instead be a list of parts (boxes and cylinders, joined into one mesh: a chair), the floor
carries an image texture (the procedural floor colf-synth baked) and walls stand around it.
"""

import json
import math
import sys

import bpy


def srgb_to_linear(c):
    return c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4


def reset():
    bpy.ops.wm.read_factory_settings(use_empty=True)
    return bpy.context.scene


def setup_render(scene, job, width, height, aspect_x, scene_seed):
    r = scene.render
    r.engine = "CYCLES"
    scene.cycles.device = "CPU"
    r.threads_mode = "FIXED"
    r.threads = job["threads"]
    r.resolution_x = width
    r.resolution_y = height
    r.resolution_percentage = 100
    r.pixel_aspect_x = aspect_x
    r.pixel_aspect_y = 1.0
    r.dither_intensity = 0.0
    r.use_persistent_data = False
    r.image_settings.file_format = "PNG"
    r.image_settings.color_depth = "8"
    r.image_settings.compression = 0
    r.film_transparent = False
    vs = scene.view_settings
    scene.display_settings.display_device = "sRGB"
    vs.view_transform = "Standard"
    vs.look = "None"
    vs.exposure = 0.0
    vs.gamma = 1.0
    scene.sequencer_colorspace_settings.name = "sRGB"
    c = scene.cycles
    c.use_animated_seed = False
    c.use_adaptive_sampling = False
    c.use_denoising = False
    c.seed = scene_seed
    c.sample_clamp_direct = 0.0
    c.sample_clamp_indirect = 10.0


def colour_mode(scene, job):
    c = scene.cycles
    c.samples = job["samples"]
    c.max_bounces = 4
    c.diffuse_bounces = 4
    c.glossy_bounces = 2
    c.transmission_bounces = 0
    c.transparent_max_bounces = 0
    c.volume_bounces = 0
    c.caustics_reflective = False
    c.caustics_refractive = False
    c.filter_width = 1.5
    scene.render.image_settings.color_mode = "RGB"


def mask_mode(scene):
    c = scene.cycles
    c.samples = 1
    c.max_bounces = 0
    c.diffuse_bounces = 0
    c.glossy_bounces = 0
    # The one sample of each pixel lands within ±0.005 pixel of its centre.
    c.filter_width = 0.01
    scene.render.image_settings.color_mode = "BW"


def principled(name, rgb, roughness, specular):
    m = bpy.data.materials.new(name)
    m.use_nodes = True
    b = m.node_tree.nodes["Principled BSDF"]
    b.inputs["Base Color"].default_value = (rgb[0], rgb[1], rgb[2], 1.0)
    b.inputs["Roughness"].default_value = roughness
    b.inputs["Specular"].default_value = specular
    return m


def textured_floor(path):
    """A matte floor whose base colour is the image at `path` (8-bit sRGB), spread over the
    plane's UV square: the plane's corner (-, -) is the image's bottom-left."""
    m = principled("floor", (1.0, 1.0, 1.0), 1.0, 0.2)
    nodes = m.node_tree.nodes
    tex = nodes.new("ShaderNodeTexImage")
    tex.image = bpy.data.images.load(path)
    tex.image.colorspace_settings.name = "sRGB"
    tex.interpolation = "Linear"
    tex.extension = "EXTEND"
    bsdf = nodes["Principled BSDF"]
    m.node_tree.links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
    return m


def emission(name, level):
    """A flat emitter whose 8-bit sRGB value under the Standard view transform is `level`."""
    m = bpy.data.materials.new(name)
    m.use_nodes = True
    nodes = m.node_tree.nodes
    for n in list(nodes):
        nodes.remove(n)
    out = nodes.new("ShaderNodeOutputMaterial")
    e = nodes.new("ShaderNodeEmission")
    v = srgb_to_linear(level / 255.0)
    e.inputs["Color"].default_value = (v, v, v, 1.0)
    e.inputs["Strength"].default_value = 1.0
    m.node_tree.links.new(e.outputs["Emission"], out.inputs["Surface"])
    return m


def add_parts(o, index):
    """One mesh of the object's parts (boxes and cylinders, their centres relative to the
    object's position), smooth-shaded with sharp edges above 30 degrees."""
    import bmesh
    from mathutils import Matrix

    bm = bmesh.new()
    for part in o["parts"]:
        r = part["rotation"]
        rotation = Matrix([r[0:3], r[3:6], r[6:9]]).to_4x4()
        place = Matrix.Translation(part["center"]) @ rotation
        if part["kind"] == "box":
            hx, hy, hz = part["half"]
            scale = Matrix.Diagonal((hx, hy, hz, 1.0))
            bmesh.ops.create_cube(bm, size=2.0, matrix=place @ scale)
        elif part["kind"] == "cylinder":
            rad, hh = part["radius"], part["half_height"]
            scale = Matrix.Diagonal((rad, rad, hh, 1.0))
            bmesh.ops.create_cone(
                bm,
                cap_ends=True,
                cap_tris=False,
                segments=64,
                radius1=1.0,
                radius2=1.0,
                depth=2.0,
                matrix=place @ scale,
            )
        else:
            raise ValueError("unknown part kind %r" % part["kind"])
    mesh = bpy.data.meshes.new("object_%d" % index)
    bm.to_mesh(mesh)
    bm.free()
    for poly in mesh.polygons:
        poly.use_smooth = True
    mesh.use_auto_smooth = True
    mesh.auto_smooth_angle = math.radians(30.0)
    ob = bpy.data.objects.new("object_%d" % index, mesh)
    bpy.context.scene.collection.objects.link(ob)
    ob.location = o["position"]
    return ob


def add_object(o, index):
    if "parts" in o:
        return add_parts(o, index)
    shape, r = o["shape"], o["size"]
    x, y, z = o["position"]
    if shape == "sphere":
        bpy.ops.mesh.primitive_uv_sphere_add(segments=64, ring_count=32, radius=r)
        bpy.ops.object.shade_smooth()
    elif shape == "cube":
        bpy.ops.mesh.primitive_cube_add(size=2.0 * r / math.sqrt(2.0))
    elif shape == "cylinder":
        bpy.ops.mesh.primitive_cylinder_add(vertices=64, radius=r, depth=2.0 * r)
        bpy.ops.object.shade_smooth()
        ob = bpy.context.active_object
        ob.data.use_auto_smooth = True
        ob.data.auto_smooth_angle = math.radians(30.0)
    else:
        raise ValueError("unknown shape %r" % shape)
    ob = bpy.context.active_object
    ob.name = "object_%d" % index
    ob.location = (x, y, z)
    ob.rotation_euler = (0.0, 0.0, math.radians(o["rotation_z_degrees"]))
    return ob


def add_area_light(name, light):
    data = bpy.data.lights.new(name, type="AREA")
    data.energy = light["energy"]
    data.size = light["size"]
    data.color = (1.0, 1.0, 1.0)
    ob = bpy.data.objects.new(name, data)
    bpy.context.scene.collection.objects.link(ob)
    ob.location = light["position"]
    # Point the light (which shines along its local −Z) at its target.
    direction = [t - p for t, p in zip(light["target"], light["position"])]
    from mathutils import Vector

    ob.rotation_euler = Vector(direction).to_track_quat("-Z", "Y").to_euler()
    return ob


def set_camera(scene, cam, view, width):
    from mathutils import Matrix

    m = view["camera_to_world"]
    cam.matrix_world = Matrix([m[0:4], m[4:8], m[8:12], m[12:16]])
    cam.data.sensor_fit = "HORIZONTAL"
    cam.data.sensor_width = 36.0
    cam.data.lens = 36.0 * view["fl_x"] / width
    cam.data.shift_x = 0.0
    cam.data.shift_y = 0.0
    cam.data.clip_start = 0.1
    cam.data.clip_end = 1000.0


def render_to(scene, path):
    scene.render.filepath = path
    bpy.ops.render.render(write_still=True)


def render_scene(job, s):
    scene = reset()
    setup_render(scene, job, s["width"], s["height"], s["pixel_aspect_x"], s["cycles_seed"])
    world = bpy.data.worlds.new("world")
    world.use_nodes = True
    bg = world.node_tree.nodes["Background"]
    g = s["ambient"]
    bg.inputs["Color"].default_value = (g, g, g, 1.0)
    scene.world = world

    bpy.ops.mesh.primitive_plane_add(size=s["floor_size"], location=(0.0, 0.0, 0.0))
    floor = bpy.context.active_object
    if s.get("floor_texture"):
        floor.data.materials.append(textured_floor(s["floor_texture"]))
    else:
        fa = s["floor_albedo"]
        floor.data.materials.append(principled("floor", fa, 1.0, 0.2))
    background = [floor]
    for k, w in enumerate(s.get("walls", [])):
        bpy.ops.mesh.primitive_cube_add(size=2.0, location=w["center"])
        wall = bpy.context.active_object
        wall.name = "wall_%d" % k
        wall.scale = w["half"]
        wall.data.materials.append(principled("wall_%d" % k, w["albedo"], 1.0, 0.2))
        background.append(wall)

    objects = []
    for i, o in enumerate(s["objects"]):
        ob = add_object(o, i + 1)
        ob.data.materials.append(principled("rubber_%d" % (i + 1), o["albedo"], 0.9, 0.2))
        objects.append(ob)
    lights = [add_area_light(name, s["lights"][name]) for name in ("key", "fill", "back")]

    cam_data = bpy.data.cameras.new("camera")
    cam = bpy.data.objects.new("camera", cam_data)
    scene.collection.objects.link(cam)
    scene.camera = cam

    passes = [(None, s["views"])]
    if s.get("moved"):
        passes.append((s["moved"], s["moved"]["views"]))

    def colour_and_mask(views):
        colour_mode(scene, job)
        for view in views:
            set_camera(scene, cam, view, s["width"])
            render_to(scene, view["rgb"])
        saved = [list(ob.data.materials) for ob in objects]
        background_saved = [list(ob.data.materials) for ob in background]
        for i, ob in enumerate(objects):
            ob.data.materials.clear()
            ob.data.materials.append(emission("id_%d" % (i + 1), s["objects"][i]["mask_level"]))
        black = emission("id_0", 0)
        for ob in background:
            ob.data.materials.clear()
            ob.data.materials.append(black)
        bg.inputs["Strength"].default_value = 0.0
        for lt in lights:
            lt.hide_render = True
        mask_mode(scene)
        for view in views:
            set_camera(scene, cam, view, s["width"])
            render_to(scene, view["mask"])
        for ob, mats in zip(objects + background, saved + background_saved):
            ob.data.materials.clear()
            for m in mats:
                ob.data.materials.append(m)
        bg.inputs["Strength"].default_value = 1.0
        for lt in lights:
            lt.hide_render = False

    for moved, views in passes:
        if moved is None:
            colour_and_mask(views)
        else:
            ob = objects[moved["object"] - 1]
            before = tuple(ob.location)
            ob.location = tuple(b + d for b, d in zip(before, moved["by"]))
            colour_and_mask(views)
            ob.location = before


def main():
    argv = sys.argv[sys.argv.index("--") + 1 :] if "--" in sys.argv else []
    if len(argv) != 1:
        raise SystemExit("usage: blender -b --python blender_clevr.py -- JOB.json")
    with open(argv[0]) as f:
        job = json.load(f)
    for s in job["scenes"]:
        render_scene(job, s)
        # uORF's scene manipulation: other objects and lights seen from this scene's cameras.
        for extra in s.get("extra_scenes", []):
            render_scene(job, dict(s, moved=None, **extra))
        print("colf-scene-done %d" % s["index"], flush=True)


main()
