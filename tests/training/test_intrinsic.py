"""The intrinsic model's data, network, losses and export, and the renderer against the light
stage: with the light stage's exact buffers the renderer must put the light where the light
stage does (this is what pins the normal, image and light-vector axes to each other)."""

import numpy as np
import pytest
import torch

from addon import contract, intrinsic, lightvec

RES = 64


@pytest.fixture(scope="module")
def frames(shared_data, tmp_path_factory):
    from training.intrinsic import data

    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("intrinsic")
    data.build("val", RES, 2, out, data_root=shared_data, progress=None)
    return data.IntrinsicFrames("val", RES, 0, out, shared_data)


def test_samples_hold_the_exact_buffers(frames):
    from training.intrinsic import data

    s = frames[0]
    assert s["image"].shape == (3, RES, RES) and s["target"].shape == (26, RES, RES)
    assert np.isfinite(s["image"]).all() and (s["image"] >= 0).all()
    fg = s["fg"][0] > 0
    assert fg.mean() > 0.1
    n = s["target"][0:3][:, fg]
    np.testing.assert_allclose(np.linalg.norm(n, axis=0), 1.0, atol=1e-3)
    assert (n[2] > -1e-3).all()  # every visible normal faces the camera
    assert set(np.unique(s["target"][8])) <= {0.0, 1.0} and s["target"][8].max() == 1.0  # face
    assert (s["target"][0:3][:, ~fg] == 0).all()  # no buffers where there is no subject
    # Deterministic per index, different across indices.
    np.testing.assert_array_equal(frames[5]["image"], frames[5]["image"])
    assert not np.array_equal(frames[5]["image"], frames[6]["image"])
    assert data.TARGETS == ("normal", "height", "albedo", "matte", "face", "transfer", "hair")
    assert (s["target"][data.TRANSFER][:, ~fg] == 0).all()


def test_the_hair_label_follows_the_light_stage_s_and_the_mirror(frames):
    """The target's last channel is the light stage's hair label, mirrored with the picture
    when the sample is; it lies on the subject and never on face skin."""
    from training.intrinsic import data
    from training.intrinsic.model import HAIR_TARGET

    assert HAIR_TARGET == data.TRANSFER.stop  # right after the transfer's channels
    truths = [(frames.frame(k)["label"] == data.HAIR).astype(np.float32) for k in range(frames.n)]
    for i in range(4):
        s = frames[i]
        hair = s["target"][HAIR_TARGET]
        assert any(np.array_equal(hair, t) or np.array_equal(hair, t[:, ::-1]) for t in truths)
        assert (hair * s["target"][8]).max() == 0.0  # not face skin
        assert (hair <= s["fg"][0]).all()
    assert max(frames[i]["target"][HAIR_TARGET].mean() for i in range(4)) > 0.01


def test_the_card_s_buffer_figures_include_the_hair_class(frames):
    """export.val_metrics of a forward that returns the light stage's own buffers: every
    buffer exact, hair included (hair_iou 1), beside the transfer's figures."""
    from training.intrinsic import export
    from training.intrinsic.model import HAIR_TARGET

    cache = frames.folder.parent

    def truth(x):
        t = export.val_inputs(len(x), RES, cache)[0]["target"]
        parsing = torch.cat([t[:, 7:9], t[:, HAIR_TARGET:HAIR_TARGET + 1]], 1)
        return t[:, 0:3], t[:, 3:4], t[:, 4:7], parsing, t[:, 9:HAIR_TARGET]

    m = export.val_metrics(truth, 2, RES, cache)
    assert m["hair_iou"] == 1.0 and m["matte_iou"] == 1.0 and m["face_iou"] == 1.0
    assert m["transfer_abs"] == 0.0 and m["albedo_log_abs"] < 1e-6


def test_a_network_given_the_hair_class_keeps_every_other_output(frames):
    """IntrinsicNet(hair=True) loaded from a network without the class gives that network's
    outputs exactly and a third parsing channel; --train-only hair leaves only the hair head to
    train; its loss joins the total."""
    from training.intrinsic.model import IntrinsicNet, has_hair, load_weights, losses
    from training.intrinsic.train import frozen_modules

    torch.manual_seed(0)
    old = IntrinsicNet("small").eval()
    net = IntrinsicNet("small", hair=True).eval()
    load_weights(net, old.state_dict())
    assert has_hair(net.state_dict()) and not has_hair(old.state_dict())
    assert net.classes == ("foreground", "skin", "hair")
    b = frames.batch(range(2))
    x = b["image"] / b["image"].amax()
    with torch.no_grad():
        ref, got = old(x), net(x)
    for r, g in zip(ref, got):
        torch.testing.assert_close(r, g[:, :r.shape[1]], rtol=0, atol=0)
    assert got[3].shape == (2, 3, RES, RES)
    frozen_modules(net, "hair")
    trainable = {n for n, p in net.named_parameters() if p.requires_grad}
    assert trainable and all(n.startswith("hair_head.") for n in trainable)
    ls = losses(got, b["target"], b["fg"])
    assert float(ls["hair"]) > 0.1
    assert float(losses(ref, b["target"], b["fg"])["hair"]) == 0.0


def test_a_network_given_the_albedo_head_starts_as_it_was_and_trains_only_that(frames):
    """IntrinsicNet(albedo=True) loaded from a network without the head gives that network's
    outputs exactly (the head's last convolution starts at zero); --train-only albedo leaves only
    the head to train, and a step of the albedo loss changes the albedo alone."""
    from training.intrinsic.model import IntrinsicNet, has_albedo_head, load_weights, losses
    from training.intrinsic.train import frozen_modules, training_mode

    torch.manual_seed(0)
    old = IntrinsicNet("small", hair=True).eval()
    net = IntrinsicNet("small", hair=True, albedo=True)
    load_weights(net, old.state_dict())
    assert has_albedo_head(net.state_dict()) and not has_albedo_head(old.state_dict())
    b = frames.batch(range(2))
    x = b["image"] / b["image"].amax()
    with torch.no_grad():
        ref, got = old(x), net.eval()(x)
    for r, g in zip(ref, got):
        torch.testing.assert_close(r, g, rtol=0, atol=0)
    frozen = frozen_modules(net, "albedo")
    trainable = {n for n, p in net.named_parameters() if p.requires_grad}
    assert trainable and all(n.startswith("albedo_head.") for n in trainable)
    training_mode(net, frozen)
    opt = torch.optim.SGD([p for p in net.parameters() if p.requires_grad], lr=1.0)
    for _ in range(2):  # the first step moves only the zero last layer; the second, the rest
        opt.zero_grad()
        losses(net(x), b["target"], b["fg"])["albedo"].backward()
        opt.step()
    with torch.no_grad():
        after = net.eval()(x)
    for i, (r, g) in enumerate(zip(ref, after)):
        if i == 2:
            assert float((g - r).abs().mean()) > 1e-4
        else:
            torch.testing.assert_close(r, g, rtol=0, atol=0)


def test_the_transfer_is_the_light_stages_irradiance_to_its_order(frames):
    """transfer . light_sh(light) gives the irradiance the light stage's own transport gives
    (its 114 lights' visibility x cosine) within the SH order's error; a uniform world exactly
    (order 0). It carries occlusion: under a uniform world a skin pixel's irradiance is its
    sky's visible share, below the unoccluded pi in a crease and never above it (hair's wrapped
    lobe takes more)."""
    from bench.intrinsic_effects import lamp
    from training.intrinsic import data
    from training.lightstage import layout

    a = frames.frame(0)
    m = a["mask"]
    t = data.transfer(a)
    for light, tol in ((lightvec.uniform(), 1e-3), (lamp([-1, 0.3, 0.5]), 0.12)):
        truth = data.dense(a, a["diffuse"].astype(np.float32) @ layout.weights(light).astype(
            np.float32))
        got = intrinsic.transfer_irradiance(light.astype(np.float32), t)
        rel = np.sqrt(((got - truth)[:, m] ** 2).mean() / (truth[:, m] ** 2).mean())
        assert rel < tol, rel
    skin = m & (a["label"] == data.SKIN)
    e = intrinsic.transfer_irradiance(lightvec.uniform().astype(np.float32), t)[1][skin]
    assert e.max() <= np.pi * 1.01 and np.percentile(e, 5) < 0.8 * np.pi


def test_the_flip_mirrors_the_transfer(frames):
    """A sample's transfer is its frame's, or, where the sample is mirrored, the mirrored
    subject's (x-odd coefficients negated): lit by a lamp from the left it shades as the
    frame does under the same lamp from the right."""
    from bench.intrinsic_effects import lamp
    from training.intrinsic import data

    plain = [data.transfer(frames.frame(j)) for j in range(frames.n)]
    mirrored = []
    for t in plain:
        tf = t[..., ::-1].copy()
        tf[list(intrinsic.TRANSFER_X_ODD)] *= -1.0
        mirrored.append(tf)
    seen = set()
    for i in range(24):
        got = frames[i]["target"][data.TRANSFER]
        kinds = {k for k, ts in (("plain", plain), ("mirrored", mirrored))
                 if any(np.allclose(got, t, atol=1e-5) for t in ts)}
        assert kinds, i
        seen |= kinds
    assert seen == {"plain", "mirrored"}
    left, right = lamp([-1, 0.3, 0.5]), lamp([1, 0.3, 0.5])
    np.testing.assert_allclose(intrinsic.transfer_irradiance(left, mirrored[0]),
                               intrinsic.transfer_irradiance(right, plain[0])[..., ::-1],
                               rtol=1e-3, atol=1e-3)


def test_the_flip_mirrors_normals(frames):
    """A flipped sample's normals point the other way in x: the flip must not teach the network
    that a face turned left has normals of one turned right."""
    for i in range(40):
        s = frames[i]
        fg = s["fg"][0] > 0
        # the mirrored image's normals: the mean x of the right-facing half is positive
        n = s["target"][0:3]
        cols = np.nonzero(fg.any(0))[0]
        mid = (cols.min() + cols.max()) / 2
        right = fg & (np.arange(RES)[None, :] > mid + 4)
        left = fg & (np.arange(RES)[None, :] < mid - 4)
        assert n[0][right].mean() > n[0][left].mean()


def test_renderer_with_exact_buffers_puts_the_light_where_the_light_stage_does(frames):
    from bench.intrinsic_effects import error, exact_buffers, lamp, render, source_light

    a = frames.frame(0)
    src = render(a, source_light())
    for d in ([-1, 0.3, 0.5], [1, 0.2, 0.6]):
        light = lamp(d)
        gt = render(a, light)
        sh = intrinsic.shade(src, exact_buffers(a), light)
        out = src * sh.ratio + sh.highlight
        assert error(out, gt, a["mask"]) < 0.5 * error(src, gt, a["mask"])
        # The mirrored lamp would be much worse: the axes line up.
        mirrored = lamp([-d[0], d[1], d[2]])
        sh_m = intrinsic.shade(src, exact_buffers(a), mirrored)
        assert error(out, gt, a["mask"]) < error(src * sh_m.ratio + sh_m.highlight, gt, a["mask"])


def test_losses_vanish_for_the_truth_and_the_network_gives_unit_normals(frames):
    from training.intrinsic.model import IntrinsicNet, losses

    b = frames.batch(range(3))
    t = b["target"]
    truth = (t[:, 0:3], t[:, 3:4] + 5.0, t[:, 4:7], t[:, 7:9], t[:, 9:25])
    ls = losses(truth, t, b["fg"])
    assert float(ls["normal"]) < 1e-4 and float(ls["height"]) < 1e-4  # height up to a constant
    assert float(ls["albedo"]) < 1e-5 and float(ls["transfer"]) < 1e-6
    # Albedo counts up to a gain (nearly: log(a + 0.02) keeps dark texels from dominating).
    gained = losses((truth[0], truth[1], t[:, 4:7] * 1.7, *truth[3:]), t, b["fg"])["albedo"]
    shuffled = losses((truth[0], truth[1], t[:, 4:7].flip(2), *truth[3:]), t, b["fg"])["albedo"]
    assert float(gained) < 0.3 * float(shuffled)
    net = IntrinsicNet("small")
    normal, height, albedo, parsing, transfer = net(b["image"] / b["image"].amax())
    assert normal.shape == (3, 3, RES, RES) and parsing.shape == (3, 2, RES, RES)
    assert transfer.shape == (3, 16, RES, RES)
    np.testing.assert_allclose(normal.norm(dim=1).detach().numpy(), 1.0, atol=1e-4)
    assert float(losses((normal, height, albedo, parsing, transfer), t, b["fg"])["normal"]) > 0.05


def test_the_network_transfer_starts_from_its_normals_unoccluded_one(frames):
    """The transfer head predicts what occlusion changes: a network loaded from one saved
    before the transfer existed (a head of nine channels) keeps those nine and gives the
    unoccluded transfer of its own normals, which under any light is Lambert's shading on them
    (the renderer's shading without occlusion), while the truth's unoccluded transfer is
    farther from the light stage's than the truth."""
    from training.intrinsic import data
    from training.intrinsic.model import IntrinsicNet, has_transfer, load_weights, unoccluded

    torch.manual_seed(0)
    old = IntrinsicNet("small", transfer=False).eval()
    assert not has_transfer(old.state_dict())
    net = IntrinsicNet("small").eval()
    load_weights(net, old.state_dict())
    assert has_transfer(net.state_dict())
    b = frames.batch(range(2))
    x = b["image"] / b["image"].amax()
    with torch.no_grad():
        ref, got = old(x), net(x)
    for r, g in zip(ref, got[:4]):
        torch.testing.assert_close(r, g)
    light = lightvec.uniform() * 0.3 + lightvec.splat_direction([0.5, 0.4, 0.77], [2.0] * 3)
    n = got[0][0].numpy()
    lam = intrinsic.irradiance(light.astype(np.float32), n, exact_cells=0)
    tr = intrinsic.transfer_irradiance(light.astype(np.float32), got[4][0].numpy())
    np.testing.assert_allclose(tr, lam, rtol=0.05, atol=0.05 * float(lam.max()))
    t = b["target"]
    fg = b["fg"][:, 0] > 0
    free = (unoccluded(t[:, 0:3]) - t[:, data.TRANSFER]).abs().mean(1)[fg].mean()
    assert float(free) > 0.01


def test_face_weight_and_curvature_terms_of_the_normal_loss(frames):
    """face_weight counts the face skin's normal error more; the curvature term (the normals'
    pooled neighbour differences on face skin) is nil for the truth and grows when the face is
    flattened (its normals blurred), which the plain angle barely tells from noise."""
    from training.intrinsic.model import losses, normal_gradient

    b = frames.batch(range(3))
    t, fg = b["target"], b["fg"]
    face = fg * t[:, 8:9]
    assert float(face.sum()) > 100
    truth = (t[:, 0:3], t[:, 3:4], t[:, 4:7], t[:, 7:9], t[:, 9:25])
    assert float(normal_gradient(t[:, 0:3], t[:, 0:3], face)) == 0.0
    assert float(losses(truth, t, fg, face_weight=2.0, gradient_weight=0.1)["normal"]) < 1e-4
    flat = torch.nn.functional.normalize(torch.nn.functional.avg_pool2d(
        t[:, 0:3], 9, 1, 4, count_include_pad=False), dim=1)
    assert float(normal_gradient(flat, t[:, 0:3], face)) > 0.05
    # Error on the face only: counted 1 + face_weight times as much against the same error's
    # share of the whole subject.
    on_face = torch.where(t[:, 8:9] > 0.5, flat, t[:, 0:3])
    plain = float(losses((on_face, *truth[1:]), t, fg)["normal"])
    weighted = float(losses((on_face, *truth[1:]), t, fg, face_weight=2.0)["normal"])
    assert weighted > 1.5 * plain
    curved = float(losses((on_face, *truth[1:]), t, fg, face_weight=2.0,
                          gradient_weight=0.1)["normal"])
    assert curved > weighted


def test_export_matches_torch_and_follows_the_contract(tmp_path):
    import onnxruntime as ort

    from training.intrinsic.export import check_against_torch, export_onnx
    from training.intrinsic.model import IntrinsicNet

    torch.manual_seed(0)
    net = IntrinsicNet("small").eval()
    path = tmp_path / "m.onnx"
    export_onnx(net, path)
    assert check_against_torch(net, path) < 1e-3
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    assert [i.name for i in sess.get_inputs()] == [contract.INPUT_IMAGE]
    assert [o.name for o in sess.get_outputs()] == [contract.OUTPUT_NORMAL, contract.OUTPUT_HEIGHT,
                                                    contract.OUTPUT_ALBEDO, contract.OUTPUT_PARSING,
                                                    contract.OUTPUT_TRANSFER]
    # A network without the transfer (one trained before it) exports its four buffers.
    old = IntrinsicNet("small", transfer=False).eval()
    export_onnx(old, tmp_path / "old.onnx")
    sess = ort.InferenceSession(str(tmp_path / "old.onnx"), providers=["CPUExecutionProvider"])
    assert contract.OUTPUT_TRANSFER not in [o.name for o in sess.get_outputs()]


def test_int8_export_keeps_the_named_layers_float_and_stays_near_the_float_network(frames,
                                                                                  tmp_path):
    """--int8: every convolution but INT8_KEEP_FLOAT's reads int8 weights, the file is smaller,
    its buffers stay near the float network's, and the card's record says how near."""
    import onnx

    from training.intrinsic.export import conv_nodes, export_onnx, quantise
    from training.intrinsic.model import IntrinsicNet

    torch.manual_seed(0)
    net = IntrinsicNet("small", hair=True).eval()
    fp, q8 = tmp_path / "m.float.onnx", tmp_path / "m.onnx"
    export_onnx(net, fp)
    rec = quantise(fp, q8, frames.batch(range(4)), frames.batch(range(4, 6)), RES)
    convs = conv_nodes(fp)
    keep = set(rec["kept_float"])
    # the first, the full-resolution decoder block's two, the head and the hair head's three
    assert convs[0] in keep and len(keep) == 7
    assert {c for c in convs if "/hair_head/" in c or c.startswith("/head/")} <= keep
    assert {c for c in convs if c.startswith("/dec.0/")} <= keep
    g = onnx.load(str(q8)).graph
    from_int8 = {n.output[0] for n in g.node if n.op_type == "DequantizeLinear"}
    for n in g.node:
        if n.op_type == "Conv":
            assert (n.input[1] in from_int8) == (n.name not in keep), n.name
    assert q8.stat().st_size < 0.5 * fp.stat().st_size
    near = rec["against_float"]
    assert 0 < near["normal_angle_deg_mean"] < 5 and near["parsing_abs"] < 0.02
    assert near["albedo_log_abs"] < 0.1 and near["samples"] == 2
    assert rec["ms_one_thread"]["int8"] > 0 and rec["ms_one_thread"]["float"] > 0


def test_skin_and_hair_constants_are_the_light_stage_s():
    """The renderer diffuses light under skin with the light stage's own shares and widths, and
    wraps it around hair with the light stage's lobe."""
    from training.lightstage import shading

    assert intrinsic.SSS_ALPHA == shading.SSS_ALPHA
    assert intrinsic.SSS_SIGMA_CM == shading.SSS_SIGMA_CM
    assert intrinsic.HAIR_WRAP == shading.HAIR_WRAP


def test_the_frame_cut_blacks_out_beyond_the_edge_and_drops_the_losses_there(frames):
    """A cut sample's input is black beyond its frame edge (as the product pads a crop beyond the
    frame), its buffers are not supervised there and its matte and face targets are empty there;
    inside, nothing changes; uncut samples are untouched."""
    from training.intrinsic.train import frame_cut, prepare

    batch = frames.batch(range(8))
    cut = frame_cut(batch, torch.Generator().manual_seed(0), p=1.0)
    inside = cut["inside"]
    out = inside < 0.5
    assert out.any(), "no sample was cut"
    assert (cut["fg"][out] == 0).all() and (cut["target"][:, 7:9][out.expand(-1, 2, -1, -1)] == 0).all()
    keep = inside > 0.5
    assert torch.equal(cut["fg"][keep], batch["fg"][keep])
    assert torch.equal(cut["target"][:, :7], batch["target"][:, :7])
    x = prepare(cut, torch.Generator().manual_seed(1))
    assert (x[out.expand(-1, 3, -1, -1)] == 0).all() and x[keep.expand(-1, 3, -1, -1)].abs().sum() > 0
    # The edge crosses the subject: some face pixels of a cut sample were dropped.
    assert ((batch["target"][:, 8:9] > 0.5) & out).any()
    none = frame_cut(batch, torch.Generator().manual_seed(0), p=0.0)
    assert (none["inside"] == 1).all() and torch.equal(none["fg"], batch["fg"])


def test_a_long_hair_build_is_its_own_cache_and_the_card_says_so(shared_data, tmp_path, frames):
    from training.intrinsic import data, export

    torch.set_num_threads(1)
    data.build("val", RES, 2, tmp_path, data_root=shared_data, progress=None, long_hair=1.0)
    long = data.IntrinsicFrames("val", RES, 0, tmp_path, shared_data)
    assert long.long_hair == 1.0 and frames.long_hair == 0.0
    # Built again without long hair, the frames are rendered again, not taken from the cache.
    before = data.frame_path(long.folder, 0).stat().st_mtime_ns
    data.build("val", RES, 2, tmp_path, data_root=shared_data, progress=None)
    assert data.frame_path(long.folder, 0).stat().st_mtime_ns != before
    assert data.IntrinsicFrames("val", RES, 0, tmp_path, shared_data).long_hair == 0.0
    recipe = {"width": "small", "res": 128, "cache": "cache/intrinsic-long", "steps": 10,
              "long_hair": 0.5, "out": "runs/x"}
    assert "--cache cache/intrinsic-long" in export.train_command(recipe)
    assert "50% of the identities with hair long hair" in export.training_data(recipe)
    assert "long hair" not in export.training_data({**recipe, "long_hair": 0.0})


def test_runs_from_before_the_transfer_are_remade_without_it(frames):
    """A run recorded before the transfer existed (its recipe has no "transfer") is re-run with
    --no-transfer, which trains the four buffers alone; a network without the transfer takes
    the buffers of one with it (--init across the change either way)."""
    from training.intrinsic import export, train
    from training.intrinsic.model import IntrinsicNet, has_transfer, load_weights, losses

    recipe = {"width": "small", "res": 128, "steps": 10, "out": "runs/x"}
    assert "--no-transfer" in export.train_command(recipe)
    assert "--no-transfer" not in export.train_command({**recipe, "transfer": True})
    assert train.parser().parse_args(["--out", "x", "--no-transfer"]).transfer is False
    torch.manual_seed(0)
    full = IntrinsicNet("small").eval()
    plain = IntrinsicNet("small", transfer=False).eval()
    load_weights(plain, full.state_dict())
    assert not has_transfer(plain.state_dict())
    b = frames.batch(range(2))
    x = b["image"] / b["image"].amax()
    with torch.no_grad():
        got, ref = plain(x), full(x)
    assert len(got) == 4
    for g, r in zip(got, ref):
        torch.testing.assert_close(g, r)
    ls = losses(got, b["target"], b["fg"])
    assert float(ls["transfer"]) == 0.0 and torch.isfinite(ls["total"])


def _batch_norms_set_apart(net):
    """Batch normalisations far from the identity, so that folding them into the convolutions
    (the export) changes every weight."""
    g = torch.Generator().manual_seed(1)
    for m in net.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            n = m.num_features
            m.weight.data = 0.5 + torch.rand(n, generator=g)
            m.bias.data = 0.2 * torch.randn(n, generator=g)
            m.running_mean.data = 0.2 * torch.randn(n, generator=g)
            m.running_var.data = 0.5 + torch.rand(n, generator=g)
    return net


def test_a_network_rebuilt_from_its_onnx_is_the_network(frames, tmp_path):
    """training.intrinsic.recover: the exported file's folded convolutions, read back into
    IntrinsicNet, give the network's outputs in evaluation mode, and in training mode too on
    the frames its batch normalisations were set from."""
    from training.intrinsic import recover
    from training.intrinsic.export import export_onnx
    from training.intrinsic.model import IntrinsicNet
    from training.intrinsic.train import prepare

    torch.manual_seed(0)
    net = _batch_norms_set_apart(IntrinsicNet("small")).eval()
    path = tmp_path / "m.onnx"
    export_onnx(net, path)
    x = prepare(frames.batch(range(4)), torch.Generator().manual_seed(3))
    rebuilt = recover.rebuild(path, "small", True, x).eval()
    with torch.no_grad():
        want, got = net(x), rebuilt(x)
        rebuilt.train()
        trained = rebuilt(x)
    for w, g, t in zip(want, got, trained):  # (height is in pixels, up to about ten)
        scale = max(1.0, float(w.abs().max()))
        torch.testing.assert_close(g, w, atol=2e-4 * scale, rtol=1e-3)
        torch.testing.assert_close(t, w, atol=2e-3 * scale, rtol=1e-2)
    # A file that is not this network's is refused, saying so.
    export_onnx(IntrinsicNet("standard").eval(), tmp_path / "other.onnx")
    with pytest.raises(ValueError, match="enc.0.0 has shape"):
        recover.rebuild(tmp_path / "other.onnx", "small", True, x)


def test_a_network_with_the_hair_class_exports_and_is_rebuilt_from_its_file(frames, tmp_path):
    """The hair class's network exports three parsing channels, and recover rebuilds it from
    the file (its hair head's convolutions included) as it rebuilds one without the class."""
    from training.intrinsic import recover
    from training.intrinsic.export import export_onnx, outputs
    from training.intrinsic.model import IntrinsicNet
    from training.intrinsic.train import prepare

    torch.manual_seed(0)
    net = _batch_norms_set_apart(IntrinsicNet("small", hair=True)).eval()
    assert dict(outputs(net))[contract.OUTPUT_PARSING] == 3
    path = tmp_path / "hair.onnx"
    export_onnx(net, path)
    x = prepare(frames.batch(range(2)), torch.Generator().manual_seed(3))
    rebuilt = recover.rebuild(path, "small", True, x, hair=True).eval()
    with torch.no_grad():
        want, got = net(x), rebuilt(x)
    assert got[3].shape[1] == 3
    for w, g in zip(want, got):
        scale = max(1.0, float(w.abs().max()))
        torch.testing.assert_close(g, w, atol=2e-4 * scale, rtol=1e-3)
    with pytest.raises(ValueError, match="convolutions"):
        recover.rebuild(path, "small", True, x)  # read as a network without the class


def _float_and_int8(net, frames, tmp_path):
    """``net`` exported float (base.float.onnx) and quantised to int8 (base.onnx)."""
    from training.intrinsic.export import export_onnx, quantise

    fp, q8 = tmp_path / "base.float.onnx", tmp_path / "base.onnx"
    export_onnx(net, fp)
    quantise(fp, q8, frames.batch(range(4)), frames.batch(range(4, 6)), RES)
    return fp, q8


def test_a_hair_head_grafted_onto_a_file_leaves_its_other_outputs_bit_for_bit(frames, tmp_path):
    """graft: the base file (float, and int8) with the hair head added gives the base file's
    outputs exactly and a third parsing channel that is the hair network's own (on a float base,
    to float rounding); recover rebuilds the grafted file as a network with the class; a file
    that already has one is refused."""
    import onnxruntime as ort

    from training.intrinsic import graft, recover
    from training.intrinsic.model import IntrinsicNet, load_weights
    from training.intrinsic.train import prepare

    torch.manual_seed(0)
    base_net = _batch_norms_set_apart(IntrinsicNet("small")).eval()
    net = IntrinsicNet("small", hair=True).eval()
    load_weights(net, base_net.state_dict())
    x = prepare(frames.batch(range(2)), torch.Generator().manual_seed(3))
    fp, q8 = _float_and_int8(base_net, frames, tmp_path)
    with torch.no_grad():
        want = [t.numpy() for t in net(x)]
    for base in (fp, q8):
        out = tmp_path / f"grafted-{base.name}"
        graft.graft(base, net, out)

        def run(path):
            s = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
            return s.run(None, {contract.INPUT_IMAGE: x.numpy()})

        before, after = run(base), run(out)
        assert after[3].shape[1] == 3
        c = graft.check(before, after, want[3])
        assert c["other_outputs_max_abs_against_base"] == 0.0
        if base == fp:
            assert c["hair_mean_abs_against_the_network"] < 1e-5
            for w, g in zip(want, after):
                np.testing.assert_allclose(g, w, atol=1e-4 * max(1.0, float(np.abs(w).max())))
        else:  # the int8 layers' features feed it: near, not equal
            assert c["hair_mean_abs_against_the_network"] < 0.05
    rebuilt = recover.rebuild(tmp_path / "grafted-base.float.onnx", "small", True, x, hair=True)
    with torch.no_grad():
        np.testing.assert_allclose(rebuilt.eval()(x)[3].numpy(), want[3], atol=1e-4)
    with pytest.raises(ValueError, match="already"):
        graft.graft(tmp_path / "grafted-base.onnx", net, tmp_path / "twice.onnx")


def test_an_albedo_head_grafted_onto_a_file_leaves_its_other_outputs_bit_for_bit(frames, tmp_path):
    """graft_albedo: the base file (float, and int8, with a hair head) with the albedo's head
    added gives the base file's other outputs exactly and the network's own albedo (on a float
    base, to float rounding); recover rebuilds the grafted file with the head; a file that
    already has one is refused."""
    import onnxruntime as ort

    from training.intrinsic import graft, recover
    from training.intrinsic.model import IntrinsicNet, load_weights
    from training.intrinsic.train import prepare

    torch.manual_seed(0)
    base_net = _batch_norms_set_apart(IntrinsicNet("small", hair=True)).eval()
    net = IntrinsicNet("small", hair=True, albedo=True).eval()
    load_weights(net, base_net.state_dict())
    g = torch.Generator().manual_seed(2)
    with torch.no_grad():  # a head that changes the albedo, as a trained one does
        for p in net.albedo_head.parameters():
            p.copy_(0.3 * torch.randn(p.shape, generator=g))
    x = prepare(frames.batch(range(2)), torch.Generator().manual_seed(3))
    fp, q8 = _float_and_int8(base_net, frames, tmp_path)
    with torch.no_grad():
        want = [t.numpy() for t in net(x)]
        plain = base_net(x)[2].numpy()
    for base in (fp, q8):
        out = tmp_path / f"grafted-{base.name}"
        assert not graft.has_albedo_head(base)
        graft.graft_albedo(base, net, out)
        assert graft.has_albedo_head(out)

        def run(path):
            s = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
            return s.run(None, {contract.INPUT_IMAGE: x.numpy()})

        before, after = run(base), run(out)
        c = graft.check_albedo(before, after, want[2])
        assert c["other_outputs_max_abs_against_base"] == 0.0
        assert c["albedo_mean_abs_against_base"] > 0.01  # the head acts
        if base == fp:
            assert c["albedo_mean_abs_against_the_network"] < 1e-5
        else:  # the int8 layers' features feed it: near, not equal
            assert c["albedo_mean_abs_against_the_network"] < 0.05
            assert (np.abs(after[2] - want[2]).mean()
                    < 0.2 * np.abs(after[2] - plain).mean())
    rebuilt = recover.rebuild(tmp_path / "grafted-base.float.onnx", "small", True, x, hair=True)
    assert rebuilt.albedo
    with torch.no_grad():
        np.testing.assert_allclose(rebuilt.eval()(x)[2].numpy(), want[2], atol=1e-4)
    with pytest.raises(ValueError, match="already"):
        graft.graft_albedo(tmp_path / "grafted-base.onnx", net, tmp_path / "twice.onnx")


def test_a_network_rebuilt_from_its_int8_file_stays_near_it(frames, tmp_path):
    """An int8 file's weights are dequantised per output channel: the rebuilt float network is
    as near the int8 file as the float network it was quantised from."""
    from training.intrinsic import recover
    from training.intrinsic.export import export_onnx, quantise
    from training.intrinsic.model import IntrinsicNet
    from training.intrinsic.train import prepare

    torch.manual_seed(0)
    net = _batch_norms_set_apart(IntrinsicNet("small")).eval()
    fp, q8 = tmp_path / "m.float.onnx", tmp_path / "m.onnx"
    export_onnx(net, fp)
    quantise(fp, q8, frames.batch(range(4)), frames.batch(range(4, 6)), RES)
    x = prepare(frames.batch(range(4)), torch.Generator().manual_seed(3))
    rebuilt = recover.rebuild(q8, "small", True, x)
    near = recover.distance(rebuilt, q8, x)["eval"]
    ref = recover.distance(net, q8, x)["eval"]
    for name, d in near.items():
        assert d <= 1.5 * ref[name] + 1e-5, (name, d, ref[name])
    # each weight within one quantisation step (half a step, rounded) of the float network's
    folded = recover.conv_weights(fp)
    for name, (w, _) in recover.conv_weights(q8).items():
        step = np.abs(folded[name][0]).reshape(len(w), -1).max(1) / 127.0
        assert np.all(np.abs(w - folded[name][0]).reshape(len(w), -1).max(1) <= step + 1e-7), name


def test_a_recovered_checkpoint_trains_on_and_its_card_names_where_it_came_from(frames, tmp_path):
    """recover.save writes what train --init loads, and export.lineage of a run started from it
    records the file it was rebuilt from and, nested, the runs behind that file."""
    from training.intrinsic import export, recover
    from training.intrinsic.model import IntrinsicNet, load_weights
    from training.intrinsic.train import prepare

    torch.manual_seed(0)
    net = IntrinsicNet("small").eval()
    path = tmp_path / "m.onnx"
    export.export_onnx(net, path)
    x = prepare(frames.batch(range(2)), torch.Generator().manual_seed(3))
    rebuilt = recover.rebuild(path, "small", True, x)
    before = {"recipe": {"command": "python -m training.intrinsic.train --out runs/a",
                         "args": {"out": "runs/a"}, "git_commit": "abc", "render_version": "v2",
                         "exported_checkpoint": {"file": "best.pt", "step": 7},
                         "init": {"checkpoint": "runs/z/best.pt", "recipe": "python -m z"}}}
    rec = tmp_path / "recovered"
    recover.save(rebuilt, rec, path, before, {}, "python -m training.intrinsic.recover ...")
    again = IntrinsicNet("small")
    load_weights(again, torch.load(rec / "best.pt", map_location="cpu")["state_dict"])
    run = tmp_path / "run"
    run.mkdir()
    (run / "recipe.json").write_text(__import__("json").dumps(
        {"width": "small", "res": 128, "steps": 10, "out": str(run), "transfer": True,
         "init": str(rec / "best.pt")}))
    torch.save({"state_dict": again.state_dict(), "step": 10}, run / "best.pt")
    line = export.lineage(run, "best.pt")
    init = line["init"]
    assert init["recipe"].startswith("python -m training.intrinsic.recover")
    assert init["recovered_from"]["sha256"] == __import__("hashlib").sha256(
        path.read_bytes()).hexdigest()
    assert init["step"] == 7
    assert init["init"]["recipe"] == before["recipe"]["command"]
    assert init["init"]["checkpoint"] == "runs/a/best.pt"
    assert init["init"]["init"] == before["recipe"]["init"]
    # exported as it is (the shipped model again): its record names its folder like a run's
    direct = export.lineage(rec, "best.pt")
    assert direct["args"]["out"] == str(rec) and direct["init"]["step"] == 7


def test_a_run_keeps_its_averaged_weights_every_few_steps(frames, shared_data, tmp_path):
    """--keep-every: the averaged weights at those validation steps stay beside best.pt (a run
    is chosen on real faces too, not on its synthetic val loss alone); without it, none."""
    from training.intrinsic import data, train

    root = frames.folder.parent
    data.build("train", RES, 2, root, data_root=shared_data, progress=None)
    base = ["--width", "small", "--res", str(RES), "--cache", str(root), "--steps", "4",
            "--batch", "2", "--val-n", "2", "--val-every", "2", "--log-every", "100"]
    kept = train.train(train.parser().parse_args([*base, "--out", str(tmp_path / "a"),
                                                  "--keep-every", "2"]))
    assert sorted(p.name for p in kept.glob("step_*.pt")) == ["step_000002.pt", "step_000004.pt"]
    last, final = (torch.load(p, map_location="cpu") for p in (kept / "step_000004.pt",
                                                                kept / "checkpoint.pt"))
    assert last["step"] == 4 and final["step"] == 4
    for k, v in final["state_dict"].items():
        torch.testing.assert_close(last["state_dict"][k], v)
    first = torch.load(kept / "step_000002.pt", map_location="cpu")
    assert any(not torch.equal(first["state_dict"][k], v)
               for k, v in final["state_dict"].items() if v.dtype.is_floating_point)
    plain = train.train(train.parser().parse_args([*base, "--out", str(tmp_path / "b")]))
    assert not list(plain.glob("step_*.pt")) and (plain / "best.pt").is_file()


def test_sky_flip_turns_environments_upside_down(frames):
    """--sky-flip: an environment drawn for a sample is its own mirror image top to bottom (its
    sky below), and the light-stage render follows; without it, samples are drawn as before."""
    from training.intrinsic import data

    flips = 0
    for seed in range(40):
        plain = data.sample_light(np.random.default_rng(seed), frames.bank, frames.pool)
        turned = data.sample_light(np.random.default_rng(seed), frames.bank, frames.pool, 1.0)
        if np.random.default_rng(seed).random() < 0.35:  # the environment-only draws
            np.testing.assert_array_equal(turned, plain[::-1])
            up = lightvec.directions()[..., 1]
            power = (plain @ np.asarray(intrinsic.LUMA)) * lightvec.solid_angles()
            flipped = (turned @ np.asarray(intrinsic.LUMA)) * lightvec.solid_angles()
            assert (up * flipped).sum() == pytest.approx(-(up * power).sum(), rel=1e-5)
            flips += 1
    assert flips >= 5
    np.testing.assert_array_equal(
        data.sample_light(np.random.default_rng(3), frames.bank, frames.pool, 0.0),
        data.sample_light(np.random.default_rng(3), frames.bank, frames.pool))


def test_studio_lamps_are_one_near_white_lamp_from_the_front(frames):
    """--studio: a studio lighting is one lamp from the camera's side of the subject, within
    STUDIO_AZIMUTH and STUDIO_ELEVATION, its channels within 10% of each other, over an
    environment of at most a tenth of its own; the lamps cover lights from below and above.
    Without it, samples are drawn as before."""
    from training.intrinsic import data

    d = lightvec.directions().reshape(-1, 3)
    ups = []
    for seed in range(30):
        lamp = data.studio_lamp(np.random.default_rng(seed))
        power = (lamp.reshape(-1, 3) * lightvec.solid_angles().reshape(-1, 1)).sum(0)
        assert power.max() / power.min() < 1.1 / 0.9 + 1e-3  # near white
        lum = lamp.reshape(-1, 3) @ np.asarray(intrinsic.LUMA) * lightvec.solid_angles().ravel()
        centre = (lum[:, None] * d).sum(0) / lum.sum()
        centre /= np.linalg.norm(centre)
        azimuth = np.degrees(np.arctan2(centre[0], centre[2]))
        assert abs(azimuth) <= data.STUDIO_AZIMUTH + 12  # the lamp's splat spans cells
        ups.append(centre[1])
        # The same draw through sample_light: that lamp plus a faint environment (the
        # environment's own gain is at most 4 x e^0.45 per channel, times at most 0.1 here).
        rng = np.random.default_rng(seed)
        lit = data.sample_light(rng, frames.bank, frames.pool, 0.0, 1.0)
        rng = np.random.default_rng(seed)
        rng.random()
        rest = lit - data.studio_lamp(rng)
        assert rest.min() > -1e-5 and rest.max() <= 0.1 * 4 * np.exp(0.6) * frames.bank.max()
    assert min(ups) < -0.3 and max(ups) > 0.8
    np.testing.assert_array_equal(
        data.sample_light(np.random.default_rng(3), frames.bank, frames.pool, 0.0, 0.0),
        data.sample_light(np.random.default_rng(3), frames.bank, frames.pool))


def test_up_weight_counts_the_up_down_error_more(frames):
    """--up-weight: an error in the normals' up/down component costs up_weight times as much in
    the absolute-error part of the normal loss; an error across the face costs the same."""
    from training.intrinsic.model import losses

    b = frames.batch(range(2))
    t, fg = b["target"], b["fg"]
    truth = (t[:, 0:3], t[:, 3:4], t[:, 4:7], t[:, 7:9], t[:, 9:25])
    assert float(losses(truth, t, fg, up_weight=3.0)["normal"]) < 1e-4

    def tilted(axis):
        n = t[:, 0:3].clone()
        n[:, axis] += 0.2
        return (torch.nn.functional.normalize(n, dim=1), *truth[1:])

    for axis, factor in ((1, 3.0), (0, 1.0)):
        plain = losses(tilted(axis), t, fg)["normal"]
        weighted = losses(tilted(axis), t, fg, up_weight=3.0)["normal"]
        if factor == 1.0:
            assert float(weighted) > float(plain) - 1e-6
            assert float(weighted) < 1.2 * float(plain)
        else:
            assert float(weighted) > 1.3 * float(plain)


def test_low_band_loss_sees_the_faces_broad_shape_not_its_detail():
    """--low-weight: the normals' low band (normal_low_band) is blind to a pixel-scale ripple
    that the per-pixel loss pays for, pays for a broad tilt, and ignores the backdrop: the
    predicted normals off the subject change nothing, nor do the truth's."""
    from training.intrinsic.model import losses, masked_low, normal_low_band

    h = w = 48
    fg = torch.zeros(1, 1, h, w)
    fg[..., 8:40, 10:38] = 1.0
    yy = torch.linspace(-0.5, 0.5, h).view(1, 1, h, 1).expand(1, 1, h, w)
    unit = torch.nn.functional.normalize
    truth = unit(torch.cat([torch.zeros_like(yy), yy, torch.ones_like(yy)], 1), dim=1)

    def with_y(dy):
        n = truth.clone()
        n[:, 1:2] += dy
        return unit(n, dim=1)

    sign = (torch.arange(w) % 2 * 2 - 1).float()  # +-1 from pixel to pixel
    ripple = 0.3 * sign.view(1, 1, 1, w) * sign[:h].view(1, 1, h, 1)
    tilt = torch.full((1, 1, h, w), 0.3)
    assert float(normal_low_band(truth, truth, fg)) < 1e-6
    tilted = float(normal_low_band(with_y(tilt), truth, fg))
    assert float(normal_low_band(with_y(ripple), truth, fg)) < 0.2 * tilted
    off = with_y(tilt) * fg + with_y(-3 * tilt) * (1 - fg)
    assert float(normal_low_band(off, truth, fg)) == pytest.approx(tilted, rel=1e-5)
    assert float(normal_low_band(truth, truth * fg, fg)) < 1e-6
    low, cover = masked_low(torch.ones(1, 1, h, w), fg, 6.0)
    assert torch.allclose(low[cover > 1e-3], torch.ones(1), atol=1e-5)  # a constant, to the edge

    t = torch.cat([truth, torch.zeros(1, 6, h, w), fg, fg], 1)
    pred = (with_y(tilt), torch.zeros(1, 1, h, w), torch.full((1, 3, h, w), 0.5),
            torch.cat([fg, fg], 1))
    plain, low_w = losses(pred, t, fg)["normal"], losses(pred, t, fg, low_weight=2.0)["normal"]
    assert float(low_w - plain) == pytest.approx(2.0 * tilted, rel=1e-4)
    rippled = losses((with_y(ripple), *pred[1:]), t, fg)["normal"]
    assert float(rippled) > 0.5 * float(plain)  # which the per-pixel loss pays for


def test_albedo_weight_sets_the_albedo_terms_share_of_the_total(frames):
    """--albedo-weight: the total changes by the albedo loss times the change of its weight;
    the default is the weight the shipped network trained with."""
    from training.intrinsic.model import ALBEDO_WEIGHT, losses

    b = frames.batch(range(2))
    t, fg = b["target"], b["fg"]
    pred = (t[:, 0:3], t[:, 3:4], (t[:, 4:7] * 1.3).clamp(0, 1), t[:, 7:9], t[:, 9:25])
    base, heavy = losses(pred, t, fg), losses(pred, t, fg, albedo_weight=2.0)
    assert float(base["albedo"]) > 0.01
    assert float(heavy["total"] - base["total"]) == pytest.approx(
        (2.0 - ALBEDO_WEIGHT) * float(base["albedo"]), rel=1e-4)
    assert float(losses(pred, t, fg, albedo_weight=ALBEDO_WEIGHT)["total"]) == pytest.approx(
        float(base["total"]))


def test_train_only_last_keeps_the_rest_of_the_network_as_it_was():
    """--train-only last: a training step changes the full-resolution decoder block and the
    head, and leaves every other weight and batch statistic as it was; "all" freezes nothing."""
    from training.intrinsic.model import IntrinsicNet
    from training.intrinsic.train import frozen_modules, training_mode

    torch.manual_seed(0)
    model = IntrinsicNet("small")
    assert frozen_modules(IntrinsicNet("small"), "all") == []
    before = {k: v.clone() for k, v in model.state_dict().items()}
    frozen = frozen_modules(model, "last")
    training_mode(model, frozen)
    opt = torch.optim.SGD([p for p in model.parameters() if p.requires_grad], lr=0.1)
    for _ in range(2):
        out = model(torch.rand(2, 3, 32, 32))
        loss = sum(o.float().square().mean() for o in out)
        opt.zero_grad()
        loss.backward()
        opt.step()
    changed = {k for k, v in model.state_dict().items()
               if v.dtype.is_floating_point and not torch.equal(v, before[k])}
    assert changed and all(k.startswith(("dec.0.", "head.")) for k in changed)
    assert any(k.startswith("head.") for k in changed)
    assert any(k.startswith("dec.0.") and "running_mean" in k for k in changed)


def test_hold_others_supervises_every_buffer_but_the_albedo_by_the_init_network(frames):
    """--hold-others (held_target): the target's normals, height, parsing and transfer are the
    teacher's own prediction and its albedo the light stage's, so the teacher itself scores
    nothing but the albedo loss; a network without the hair class leaves the hair label as it
    was."""
    from training.intrinsic.model import HAIR_TARGET, IntrinsicNet, losses
    from training.intrinsic.train import held_target, prepare

    torch.manual_seed(0)
    b = frames.batch(range(2))
    x = prepare(b, torch.Generator().manual_seed(3))
    for hair in (True, False):
        teacher = IntrinsicNet("small", hair=hair).eval()
        held = held_target(teacher, x, b["target"])
        torch.testing.assert_close(held[:, 4:7], b["target"][:, 4:7], rtol=0, atol=0)
        with torch.no_grad():
            pred = teacher(x)
        torch.testing.assert_close(held[:, 0:3], pred[0], rtol=0, atol=0)
        ls = losses(pred, held, b["fg"])
        assert float(ls["normal"]) < 1e-6 and float(ls["height"]) < 1e-6
        assert float(ls["transfer"]) < 1e-6 and float(ls["albedo"]) > 0.05
        if hair:
            assert float((held[:, HAIR_TARGET] - pred[3][:, 2]).abs().max()) == 0.0
        else:
            torch.testing.assert_close(held[:, HAIR_TARGET], b["target"][:, HAIR_TARGET])
    # --learn transfer: the transfer is the light stage's too, the rest still the teacher's
    learnt = held_target(teacher, x, b["target"], ("transfer",))
    torch.testing.assert_close(learnt[:, 9:HAIR_TARGET], b["target"][:, 9:HAIR_TARGET],
                               rtol=0, atol=0)
    torch.testing.assert_close(learnt[:, 0:9], held[:, 0:9], rtol=0, atol=0)


def test_bright_crops_are_the_same_crops_normalised_brighter(frames, tmp_path):
    """--bright P: a share P of a step's crops is the crop without it times a factor between 1
    and BRIGHT_MAX / INPUT_LEVEL (their highlights clip at the network's input clamp), the rest
    and the targets exactly as without it; a step's batch still depends on (seed, step) alone."""
    from addon import intrinsic
    from training.intrinsic import export, train

    def step(*extra):
        a = train.parser().parse_args(["--out", str(tmp_path), "--res", str(RES), "--batch", "4",
                                       *extra])
        return train.step_batch(frames, a, 3)

    plain, bright, half, again = step(), step("--bright", "1"), step("--bright", "0.5"), step(
        "--bright", "0.5")
    for got in (bright, half):
        torch.testing.assert_close(got[1], plain[1], rtol=0, atol=0)
        torch.testing.assert_close(got[2], plain[2], rtol=0, atol=0)
    torch.testing.assert_close(again[0], half[0], rtol=0, atol=0)
    top = train.BRIGHT_MAX / intrinsic.INPUT_LEVEL
    lit = plain[0] > 1e-3
    factors = []
    for got in (bright, half):
        f = torch.stack([(got[0][i][lit[i]] / plain[0][i][lit[i]]).median() for i in range(4)])
        assert bool(((f >= 1 - 1e-5) & (f <= top + 1e-4)).all())
        for i in range(4):  # one factor per crop
            torch.testing.assert_close(got[0][i], plain[0][i] * f[i], rtol=1e-5, atol=1e-6)
        factors.append(f)
    assert bool((factors[0] > 1.0 + 1e-3).all())  # --bright 1: every crop brighter
    # the card's training command carries it (and the albedo's weight, which shapes a run too)
    recipe = {"width": "small", "res": 128, "steps": 10, "out": "runs/x", "bright": 0.5,
              "albedo_weight": 1.5}
    assert "--bright 0.5" in export.train_command(recipe)
    assert "--albedo-weight 1.5" in export.train_command(recipe)
    held = export.train_command({**recipe, "hold_others": True, "albedo_head": True,
                                 "train_only": "albedo", "low_weight": 2.0,
                                 "learn": ["transfer"]})
    args = train.parser().parse_args(held.split()[3:])
    assert args.hold_others and args.albedo_head and args.train_only == "albedo"
    assert args.learn == ["transfer"]
    assert args.low_weight == 2.0 and args.bright == 0.5


def test_normals_by_light_scores_the_up_down_and_left_right_shape_apart(frames):
    """bench.normals_by_light's scores: the light stage's own normals score correlation 1 and no
    angle; noise on the up/down component (a network that cannot read that shape) lowers the
    up/down correlation, leaves the left/right one, and opens the angle."""
    from bench.normals_by_light import face_scores

    s = frames[0]
    truth, face = s["target"][0:3], s["target"][8] > 0.5
    exact = face_scores(truth, truth, face)
    assert exact["corr_y"] == pytest.approx(1.0) and exact["corr_x"] == pytest.approx(1.0)
    assert exact["angle_deg"] < 0.1
    noisy = truth.copy()
    noisy[1] += np.random.default_rng(0).normal(0, 0.2, truth[1].shape)
    got = face_scores(noisy, truth, face)
    assert got["corr_y"] < 0.9 and got["corr_x"] > 0.95 and got["angle_deg"] > 3.0


def test_renderer_ceiling_ladder_rests_on_the_light_stages_own_terms(frames):
    """bench.renderer_ceiling: its diffuse and specular terms make the light stage's picture
    again; with both taken out exactly the relit frame is the truth (on the pixels the subject
    covers whole); a warm-left, cool-right source relit by a white lamp keeps its colour
    through a luminance ratio, not per channel; the renderer on exact buffers does better
    than no relighting, and better still told the source light's colour."""
    from bench.intrinsic_effects import lamp, render
    from bench.renderer_ceiling import ladder, stage_parts
    from training.intrinsic import data

    a = frames.frame(0)
    full = a["cover"] > 0.999
    warm, cool = np.array([1.0, 0.6, 0.3], np.float32), np.array([0.3, 0.6, 1.0], np.float32)
    source = (lamp([-1, 0.3, 0.6], 2.0, 0.0) * warm + lamp([1, 0.2, 0.6], 1.0, 0.0) * cool
              + 0.3 * lightvec.uniform()).astype(np.float32)
    target = lamp([0.6, 0.4, 0.7])
    e, s = stage_parts(a, source)
    albedo = data.dense(a, a["albedo"])
    picture = render(a, source)
    np.testing.assert_allclose((albedo / np.pi * e + s)[:, full], picture[:, full], rtol=1e-4,
                               atol=1e-6 * float(picture.max()))
    sample = {"img_t_i": picture, "gt_t_k": render(a, target), "light_i": source,
              "light_k": target, "mask_t": full[None].astype(np.float32)}
    got = ladder(sample, a)
    floor = got["ratio of the true diffuse shading, per channel, specular exact"]
    per_channel = got["ratio of the true diffuse shading, per channel"]
    luminance = got["ratio of the true diffuse shading"]
    assert floor < 1e-4  # (silhouette pixels, where the backdrop blends in, are left out here)
    assert per_channel < 0.7 * luminance
    assert got["renderer, exact buffers"] < 0.7 * got["input unchanged"]
    # a milder colour gradient, which source_chroma leaves to the footage (below its threshold):
    # told the light's own colour per pixel, the renderer divides it out
    mild = (lamp([-1, 0.3, 0.6], 2.0, 0.0) * np.array([1.0, 0.85, 0.7], np.float32)
            + lamp([1, 0.2, 0.6], 1.0, 0.0) * np.array([0.7, 0.85, 1.0], np.float32)
            + 0.3 * lightvec.uniform()).astype(np.float32)
    got = ladder({**sample, "img_t_i": render(a, mild), "light_i": mild}, a)
    assert (got["renderer, exact buffers, the true source light colour"]
            < got["renderer, exact buffers"])


def test_renderer_ceiling_swaps_one_exact_buffer_in_where_the_light_stage_has_it():
    """bench.renderer_ceiling.with_exact: the named buffer is the light stage's over its subject
    and the network's beyond it (the matte and face skin the light stage's whole); every other
    buffer stays the network's."""
    from addon import intrinsic
    from bench.renderer_ceiling import EXACT_ONE, with_exact

    rng = np.random.default_rng(0)

    def bufs(fill):
        n = rng.normal(size=(3, 8, 8)).astype(np.float32)
        return intrinsic.Buffers(n / np.linalg.norm(n, axis=0), np.full((8, 8), fill, np.float32),
                                 np.full((3, 8, 8), fill, np.float32),
                                 np.full((8, 8), fill, np.float32),
                                 np.full((8, 8), fill, np.float32),
                                 np.full((16, 8, 8), fill, np.float32))

    net, exact = bufs(0.25), bufs(0.75)
    cover = np.zeros((8, 8), np.float32)
    cover[2:6, 1:5] = 0.5
    on = cover > 0
    for fields in EXACT_ONE.values():
        got = with_exact(net, exact, fields, cover)
        for f in ("normal", "height", "albedo", "matte", "face", "transfer"):
            g, e, n = getattr(got, f), getattr(exact, f), getattr(net, f)
            if f not in fields:
                assert g is n
            elif f in ("matte", "face"):
                np.testing.assert_array_equal(g, e)
            else:
                np.testing.assert_array_equal(g[..., on], e[..., on])
                np.testing.assert_array_equal(g[..., ~on], n[..., ~on])


def test_batches_made_by_workers_are_the_batches_made_inline(frames, shared_data, tmp_path):
    """--workers: a step's batch is a pure function of (seed, step), so batches made ahead in
    worker processes (reading frames from the disk cache, not keeping them, or sharing the frames
    --preload read) are the inline ones, in step order."""
    from training.intrinsic import data, train

    root = frames.folder.parent
    data.build("train", RES, 2, root, data_root=shared_data, progress=None)
    a = train.parser().parse_args(["--out", str(tmp_path), "--res", str(RES), "--batch", "2",
                                   "--cut", "0.5", "--start-step", "5"])
    ds = data.IntrinsicFrames("train", RES, a.seed, root, shared_data)
    inline = train.batches(ds, a)
    first = [next(inline) for _ in range(3)]
    a.workers = 2
    lean = data.IntrinsicFrames("train", RES, a.seed, root, shared_data, keep_frames=False)
    ahead = train.batches(lean, a)
    for want in first:
        got = next(ahead)
        for w, g in zip(want, got):
            torch.testing.assert_close(g, w, rtol=0, atol=0)
    assert not lean._frames
    assert not torch.equal(first[0][0], first[1][0])
    again = train.step_batch(ds, a, 1)
    torch.testing.assert_close(again[0], first[1][0], rtol=0, atol=0)
    # --preload: the frames and their targets read once before the workers fork, shared by them
    a.preload = True
    kept = data.IntrinsicFrames("train", RES, a.seed, root, shared_data)
    kept.preload(progress=None)
    assert sorted(kept._frames) == list(range(kept.n))
    shared = train.batches(kept, a)
    for want in first:
        for w, g in zip(want, next(shared)):
            torch.testing.assert_close(g, w, rtol=0, atol=0)
    for f in kept._frames.values():  # samples (flipped or not) leave the kept target as it was
        np.testing.assert_array_equal(f[data.KEPT_TARGET], data.static_target(f))
    with pytest.raises(ValueError):
        lean.preload(progress=None)


def test_new_shadows_on_skin_are_as_warm_as_the_light_stage_s(frames, monkeypatch):
    """A lamp's new shadows on skin take the light stage's colour: over the face skin the lamp
    darkens, log(red / blue) changes from the source as in the light stage's render, within
    0.06 on average; with the diffusion's colour at its luminance's wider scale they turn warm
    (red-brown) by several times more."""
    from bench.intrinsic_effects import (darkened, exact_buffers, lamp, log_rb, render,
                                         source_light, warmth)

    errors = {}
    for f in range(2):
        a = frames.frame(f)
        src = render(a, source_light())
        src_rb = log_rb(src)
        bufs = exact_buffers(a)
        for d in ([-1, 0.3, 0.5], [1, 0.2, 0.6], [0, 1, 0.35]):
            light = lamp(d)
            gt = render(a, light)
            dark = darkened(src, gt, a["mask"] & (bufs.face > 0.5))
            truth = warmth(gt, src_rb, dark)
            assert truth is not None
            for cm in (intrinsic.SSS_CHROMA_FACE_CM, intrinsic.SSS_FACE_CM):
                monkeypatch.setattr(intrinsic, "SSS_CHROMA_FACE_CM", cm)
                sh = intrinsic.shade(src, bufs, light)
                relit = src * sh.ratio + sh.highlight
                errors.setdefault(cm, []).append(abs(warmth(relit, src_rb, dark) - truth))
            monkeypatch.undo()
    ours = np.mean(errors[intrinsic.SSS_CHROMA_FACE_CM])
    wide = np.mean(errors[intrinsic.SSS_FACE_CM])
    assert ours < 0.06 and ours < 0.5 * wide, (ours, wide)


def test_diffusion_colour_at_its_own_scale_keeps_the_luminance():
    """subsurface's three channels: their luminance is the diffusion's at SSS_FACE_CM's scale
    (what the shading's level was chosen with), their colour the narrower physical one's."""
    yy, xx = np.mgrid[0:64, 0:64].astype(np.float32)
    skin = (((yy - 32) ** 2 + (xx - 32) ** 2) < 28 ** 2).astype(np.float32)
    irr = np.repeat(0.2 + 2.0 * (xx < 32).astype(np.float32)[None], 3, 0)  # a terminator
    out = intrinsic.subsurface(irr, skin)
    px = np.sqrt(skin.sum())
    wide = intrinsic._diffuse(irr, skin, intrinsic.skin_bounds(skin > 0), intrinsic.SSS_ALPHA,
                              intrinsic.SSS_SIGMA_CM, px / intrinsic.SSS_FACE_CM)
    np.testing.assert_allclose(intrinsic.luminance(out), intrinsic.luminance(wide), atol=1e-5)
    dark = (skin > 0) & (xx >= 33) & (xx < 38)  # just past the terminator
    warm = lambda x: np.log(x[0][dark] / x[2][dark]).mean()  # noqa: E731
    assert 0 < warm(out) < 0.6 * warm(wide)


def test_init_share_averages_a_run_with_the_checkpoint_it_started_from(tmp_path):
    """export --init-share S: each float weight and batch statistic is (1 - S) the run's plus S
    its --init checkpoint's, integer counters stay the run's, and S 0 is the run itself; a run
    without --init, an init checkpoint that is not there, another network and a share outside
    [0, 1) are refused with a message."""
    from training.intrinsic import export
    from training.intrinsic.model import IntrinsicNet

    torch.manual_seed(0)
    start = IntrinsicNet("small", True, True).state_dict()
    run = {k: v + torch.randn_like(v) if v.is_floating_point() else v + 4
           for k, v in start.items()}  # batch statistics moved too
    init = tmp_path / "start.pt"
    torch.save({"state_dict": start, "width": "small"}, init)
    recipe = {"init": str(init)}
    mixed = export.with_init(run, recipe, 0.25)
    assert set(mixed) == set(run)
    for k, v in run.items():
        if v.is_floating_point():
            torch.testing.assert_close(mixed[k], 0.75 * v + 0.25 * start[k])
            assert not torch.equal(mixed[k], v)
        else:
            assert torch.equal(mixed[k], v)
    assert all(torch.equal(export.with_init(run, recipe, 0.0)[k], v) for k, v in run.items())
    torch.save({"state_dict": IntrinsicNet("small", True, False).state_dict()},
               tmp_path / "other.pt")
    for bad_recipe, share in (({}, 0.5), ({"init": str(tmp_path / "gone.pt")}, 0.5),
                              ({"init": str(tmp_path / "other.pt")}, 0.5),
                              (recipe, 1.0), (recipe, -0.1)):
        with pytest.raises(SystemExit, match="--init-share"):
            export.with_init(run, bad_recipe, share)


def test_a_quick_export_measures_no_test_set_and_its_card_loads(shared_data, tmp_path,
                                                                monkeypatch):
    """export --eval 0 (a run's snapshots, to be measured on real faces): the file and a card
    the add-on loads, the val identities' buffer errors, no test-set figures and a note saying
    so; a negative count is refused with a message."""
    import json

    from addon import engine
    from training.intrinsic import data, export, train
    from training.intrinsic.model import IntrinsicNet

    cache = tmp_path / "cache"
    data.build("val", 128, 2, cache, data_root=shared_data, progress=None)
    monkeypatch.setattr(data, "DEFAULT_OUT", cache)
    run = tmp_path / "run"
    run.mkdir()
    torch.manual_seed(0)
    net = IntrinsicNet("small", True, True)
    torch.save({"state_dict": net.state_dict(), "width": "small", "step": 7}, run / "best.pt")
    recipe = {**vars(train.parser().parse_args(["--out", str(run), "--hair"])),
              "render_version": data.renderer_version()}
    (run / "recipe.json").write_text(json.dumps(recipe))
    out = tmp_path / "models"
    export.main(["--run", str(run), "--name", "quick", "--preset", "quick", "--out", str(out),
                 "--eval", "0"])
    card = json.loads((out / "quick.json").read_text())
    assert "model" not in card["metrics"] and "--eval 0" in card["metrics"]["note"]
    assert card["metrics"]["val_buffers"]["samples"] == 96
    assert card["training"]["recipe"]["exported_checkpoint"]["step"] == 7
    assert engine.load_card(out / "quick.onnx").name == "quick"
    with pytest.raises(SystemExit):
        export.main(["--run", str(run), "--out", str(out), "--eval", "-1"])
