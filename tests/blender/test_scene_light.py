"""The bridge from a Blender scene to light vectors: sources, animation, skipping, errors."""

import math
import os

import bpy
import numpy as np
import pytest

from bench import light_conversion as lc

scene_light = lc.scene_light_module()
errors = lc.addon_module("errors")
lamps = lc.addon_module("lamps")
hdri_io = lc.addon_module("hdri_io")


def _scene():
    scene, camera, sphere = lc.referee_scene(16, 1)
    return scene, camera, sphere


def _schedule(scene, camera, sphere, frames=(1,), **kw):
    args = dict(source='LAMPS', rotation_deg=0.0, exposure=0.0, subject=sphere, camera=camera,
                subject_radius=1.0) | kw
    return scene_light.light_schedule(scene, range(frames[0], frames[-1] + 1), **args)


def test_static_lamps_are_converted_once():
    scene, camera, sphere = _scene()
    lc.add_lamp(scene, 'POINT', 4.0, energy=100.0)
    s = _schedule(scene, camera, sphere, frames=(1, 10))
    assert s.static and s.lights.shape == (1, 16, 16, 3) and s.lights.dtype == np.float32
    assert s.lights.sum() > 0 and s.skipped == []


def test_keyed_lamp_gives_one_light_per_frame_and_restores_the_frame():
    scene, camera, sphere = _scene()
    lamp = lc.add_lamp(scene, 'POINT', 4.0, energy=100.0)
    lamp.keyframe_insert("location", frame=1)
    lamp.location = (-lamp.location[0], lamp.location[1], lamp.location[2])
    lamp.keyframe_insert("location", frame=5)
    scene.frame_set(3)
    s = _schedule(scene, camera, sphere, frames=(1, 5))
    assert not s.static and s.lights.shape == (5, 16, 16, 3)
    right, left = s.lights[:, :, 9:16].sum(axis=(1, 2, 3)), s.lights[:, :, 1:8].sum(axis=(1, 2, 3))
    assert right[0] > left[0] and left[-1] > right[-1]  # the lamp crossed from right to left
    assert scene.frame_current == 3


def test_keyed_energy_on_the_light_data_is_animation_too():
    scene, camera, sphere = _scene()
    lamp = lc.add_lamp(scene, 'POINT', 4.0, energy=100.0)
    lamp.data.keyframe_insert("energy", frame=1)
    lamp.data.energy = 200.0
    lamp.data.keyframe_insert("energy", frame=3)
    s = _schedule(scene, camera, sphere, frames=(1, 3))
    assert not s.static
    np.testing.assert_allclose(s.lights[2], 2 * s.lights[0], rtol=1e-5)


def test_negligible_lamp_is_skipped_with_a_measured_error():
    scene, camera, sphere = _scene()
    lc.add_lamp(scene, 'POINT', 4.0, energy=1000.0, name="key")
    lc.add_lamp(scene, 'POINT', 4.0, direction=(-0.6, 0.2, 0.77), energy=0.05, name="dim")
    s = _schedule(scene, camera, sphere)
    assert s.skipped == ["dim"]
    with_dim = lamps.lamp_to_light(lamps.Lamp('POINT', tuple(4.0 * np.array([-0.6, 0.2, 0.77])
                                                            / np.linalg.norm([-0.6, 0.2, 0.77])),
                                              (0, 0, 1), (1, 1, 1), 0.05), 1.0) + s.lights[0]
    # What skipping costs on the sphere's shading: the dim lamp's share, 5e-5 here.
    n, inside = lc.sphere_normals(32)
    err = lc.rel_rmse(lc.shade(s.lights[0], n), lc.shade(with_dim, n), inside)
    assert 0 < err < 1e-3


def test_zero_energy_and_hidden_lamps():
    scene, camera, sphere = _scene()
    lc.add_lamp(scene, 'POINT', 4.0, energy=0.0, name="off")
    lc.add_lamp(scene, 'SUN', None, energy=3.0, name="hidden").hide_render = True
    s = _schedule(scene, camera, sphere)
    assert s.skipped == ["off"] and not s.lights.any()


def test_uniform_world_colour_and_exposure():
    scene, camera, sphere = _scene()
    bg = scene.world.node_tree.nodes["Background"]
    bg.inputs["Color"].default_value = (0.5, 0.25, 1.0, 1.0)
    bg.inputs["Strength"].default_value = 2.0
    s = _schedule(scene, camera, sphere, source='WORLD', exposure=1.0)
    expected = np.broadcast_to([2.0, 1.0, 4.0], (16, 16, 3))
    np.testing.assert_allclose(s.lights[0], expected, rtol=1e-6)


def test_world_node_it_cannot_read_is_a_clear_error():
    scene, camera, sphere = _scene()
    tree = scene.world.node_tree
    sky = tree.nodes.new('ShaderNodeTexGradient')
    tree.links.new(sky.outputs["Color"], tree.nodes["Background"].inputs["Color"])
    with pytest.raises(errors.LightingError, match="cannot read"):
        _schedule(scene, camera, sphere, source='WORLD')


def test_world_and_lamps_add_up(tmp_path):
    scene, camera, sphere = _scene()
    path = lc.write_exr(tmp_path / "sky.exr", lc.synthetic_hdri())
    lc.set_world_hdri(scene, path)
    lc.add_lamp(scene, 'SUN', None, energy=2.0)
    both = _schedule(scene, camera, sphere, source='WORLD_AND_LAMPS').lights[0]
    world = _schedule(scene, camera, sphere, source='WORLD').lights[0]
    lamp = _schedule(scene, camera, sphere, source='LAMPS').lights[0]
    np.testing.assert_allclose(both, world + lamp, rtol=1e-5, atol=1e-7)


def test_hdri_file_with_rotation_matches_world_with_mapping(tmp_path):
    scene, camera, sphere = _scene()
    path = lc.write_exr(tmp_path / "sky.exr", lc.synthetic_hdri())
    from_file = _schedule(scene, camera, sphere, source='HDRI_FILE', hdri_path=path,
                          rotation_deg=40.0).lights[0]
    lc.set_world_hdri(scene, path, mapping_z_deg=40.0)
    from_world = _schedule(scene, camera, sphere, source='WORLD').lights[0]
    np.testing.assert_allclose(from_file, from_world, rtol=1e-4, atol=1e-6)


def test_animated_rotation_callable_gives_one_light_per_frame(tmp_path):
    scene, camera, sphere = _scene()
    path = lc.write_exr(tmp_path / "sky.exr", lc.synthetic_hdri())
    s = _schedule(scene, camera, sphere, frames=(1, 3), source='HDRI_FILE', hdri_path=path,
                  rotation_deg=lambda f: 180.0 * (f - 1))
    assert not s.static and s.lights.shape[0] == 3
    np.testing.assert_allclose(s.lights[2], s.lights[0], rtol=1e-4, atol=1e-6)  # 360 degrees
    assert not np.allclose(s.lights[1], s.lights[0])


def test_builtin_hdris_are_blenders_studio_lights():
    presets = scene_light.builtin_hdris()
    assert {"studio", "forest", "city"} <= set(presets)
    assert all(os.path.isfile(p) for p in presets.values())
    scene, camera, sphere = _scene()
    s = _schedule(scene, camera, sphere, source='BUILTIN', hdri_builtin="forest")
    f = _schedule(scene, camera, sphere, source='HDRI_FILE', hdri_path=presets["forest"])
    np.testing.assert_array_equal(s.lights, f.lights)
    assert s.lights.min() >= 0 and s.lights.max() > 0


@pytest.mark.parametrize("kw,error,match", [
    (dict(source='SKY'), "InputError", "Unknown light source"),
    (dict(source='HDRI_FILE', hdri_path=None), "InputError", "no file is chosen"),
    (dict(source='HDRI_FILE', hdri_path="/nonexistent/sky.exr"), "InputError", "not found"),
    (dict(source='BUILTIN', hdri_builtin="moon"), "InputError", "studio"),
])
def test_bad_settings_are_clear_errors(kw, error, match):
    scene, camera, sphere = _scene()
    with pytest.raises(getattr(errors, error), match=match):
        _schedule(scene, camera, sphere, **kw)


def test_no_camera_needs_a_rotation():
    scene, _, sphere = _scene()
    bpy.data.objects.remove(scene.camera)
    with pytest.raises(errors.InputError, match="no camera"):
        _schedule(scene, None, sphere, source='WORLD', rotation_deg=None)
    assert _schedule(scene, None, sphere, source='WORLD', rotation_deg=0.0).static


def test_lamp_inside_the_subject_is_a_clear_error():
    scene, camera, sphere = _scene()
    lc.add_lamp(scene, 'POINT', 0.5, energy=10.0)
    with pytest.raises(errors.LightingError, match="inside the subject radius"):
        _schedule(scene, camera, sphere)


def test_subject_falls_back_to_the_camera_focus():
    scene, camera, sphere = _scene()
    lc.add_lamp(scene, 'POINT', 4.0, energy=100.0)
    by_subject = _schedule(scene, camera, sphere).lights[0]
    camera.data.dof.focus_object = sphere
    np.testing.assert_array_equal(_schedule(scene, camera, None).lights[0], by_subject)
    camera.data.dof.focus_object = None
    camera.data.dof.use_dof = True
    camera.data.dof.focus_distance = 20.0  # the camera is 20 m from the sphere's centre
    np.testing.assert_allclose(_schedule(scene, camera, None).lights[0], by_subject, rtol=1e-4,
                               atol=1e-7)
    camera.data.dof.use_dof = False
    s = _schedule(scene, camera, None)
    assert any("1 m in front of the camera" in w for w in s.warnings)


def test_camera_turn_turns_the_light_frame():
    scene, camera, sphere = _scene()
    lc.add_lamp(scene, 'SUN', None, direction=(1.0, 0.0, 0.0), energy=1.0)  # from the right
    assert _schedule(scene, camera, sphere).lights[0][:, 12].sum() > 0
    # Orbit the camera 90 degrees round to the lamp's side: the sun now faces the camera.
    camera.location = (20.0, 0.0, 0.0)
    camera.rotation_euler = (math.pi / 2, 0.0, math.pi / 2)
    light = _schedule(scene, camera, sphere).lights[0]
    assert light[:, 7:10].sum() > 0.99 * light.sum()


def test_blackbody_matches_blenders_temperature_colour():
    data = bpy.data.lights.new("t", 'POINT')
    data.use_temperature = True
    for kelvin in (2000, 3000, 4500, 6500, 9000, 12000):
        data.temperature = kelvin
        np.testing.assert_allclose(lamps.blackbody_rgb(kelvin), data.temperature_color[:],
                                   rtol=0.02, atol=0.002)
