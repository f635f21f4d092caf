"""The light stage's geometry, cosine and cast shadows against Cycles (bench/lightstage_cycles.py)."""

import pytest

pytest.importorskip("bpy")


def test_key_light_agrees_with_cycles(shared_data, tmp_path):
    import torch

    from bench import lightstage_cycles as lc

    threads = torch.get_num_threads()
    try:
        rows = {r["light"]: r for r in lc.compare(64, 16, tmp_path, shared_data)}
    finally:
        torch.set_num_threads(threads)
    key = rows["key"]["skin+clothes"]
    # Measured: ratio 0.99, relative RMSE 11% at 128 px, 10% at 64 px.
    assert 0.93 < key["mean_ratio"] < 1.07, key
    assert key["rel_rmse"] < 0.15, key  # the 128-texel shadow maps gave 16%
    assert rows["key"]["silhouette_iou"] > 0.98
    for r in rows.values():  # shadows never brighten: every light stays near or below Cycles
        assert r["skin+clothes"]["mean_ratio"] < 1.07, r
    assert (tmp_path / "cycles_side.png").is_file()


def test_skin_material_agrees_with_cycles(shared_data, tmp_path):
    """The skin's GGX lobe and subsurface scattering against Cycles' Principled BSDF with the
    stage's parameters (bench/lightstage_cycles.py compare_materials)."""
    import torch

    from bench import lightstage_cycles as lc

    threads = torch.get_num_threads()
    try:
        rows = {r["light"]: r for r in lc.compare_materials(64, 16, tmp_path, shared_data)}
    finally:
        torch.set_num_threads(threads)
    key = rows["key"]
    # Measured at 128 px, 128 samples: ours/Cycles 0.97 for the lobe alone, 1.02 with diffuse
    # (ours adds the lobe on top of the diffuse; Principled takes its energy from the diffuse).
    assert 0.85 < key["ggx"]["mean_ratio"] < 1.10, key
    assert 0.97 < key["diffuse+ggx"]["mean_ratio"] < 1.08, key
    assert key["diffuse+ggx"]["rel_rmse_box3"] < 0.15, key
    for r in rows.values():  # our subsurface never takes ours further from Cycles' random walk
        with_sss = r["diffuse+ggx+sss"]["rel_rmse_beyond_noise"]
        assert with_sss <= r["ours no sss vs cycles sss"]["rel_rmse_beyond_noise"] + 0.005, r
    assert (tmp_path / "cycles_skin_key.png").is_file()
