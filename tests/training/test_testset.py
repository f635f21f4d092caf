"""The fixed test set: rebuilt bit-identically, loaded as the dataset's samples."""

import numpy as np
import torch

RES, N = 24, 2


def test_two_builds_are_bit_identical_and_load_as_dataset_samples(shared_data, tmp_path):
    from training.data.dataset import LightStageDataset
    from training.data.make_testset import TEST_SEED, TestSet, build_testset, load_testset

    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(2)  # the build pins one thread itself
        p1, h1 = build_testset(RES, N, tmp_path / "a", shared_data)
        torch.set_num_threads(1)
        p2, h2 = build_testset(RES, N, tmp_path / "b", shared_data)
    finally:
        torch.set_num_threads(threads)
    assert h1 == h2 and len(h1) == 64
    a, b = load_testset(RES, N, tmp_path / "a"), load_testset(RES, N, tmp_path / "b")
    assert set(a) == set(b)
    for k in a:
        assert a[k].dtype == np.float32 and a[k].shape[0] == N
        np.testing.assert_array_equal(a[k], b[k])
    direct = LightStageDataset("test", RES, seed=TEST_SEED, length=N, data_root=shared_data)[1]
    ts = TestSet(RES, N, tmp_path / "a")
    assert len(ts) == N
    for k, v in direct.items():
        np.testing.assert_allclose(ts[1][k], v, rtol=1e-6, atol=1e-7, err_msg=k)


def test_a_missing_test_set_is_built_on_load(shared_data, tmp_path):
    from training.data.make_testset import load_testset, testset_path

    assert not testset_path(RES, 1, tmp_path).exists()
    s = load_testset(RES, 1, tmp_path, shared_data)
    assert testset_path(RES, 1, tmp_path).is_file()
    assert s["img_t_i"].shape == (1, 3, RES, RES) and np.isfinite(s["img_t_i"]).all()
