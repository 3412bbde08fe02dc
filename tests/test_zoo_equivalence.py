"""Independent re-statements of the published networks, written in plain torch.nn.functional from the authors'
definitions, fed the same weights the way the authors' checkpoints hold them (SafeUAV: an ordered tensor list;
the others: their state_dict key names), and compared with the zoo modules (relative error < 1e-3).

What each re-statement encodes (read from the authors' code):
- SafeUAV-Small (aistairc/SafeUAV unet_tiny_sum.py): conv+ReLU / stride-2 conv+ReLU three times; six serial
  dilated convs (1..32) whose ReLU outputs are ALL summed; per level: ReLU(convT k3 s2 p1), pad right/bottom by
  one, ADD the skip, conv+ReLU; 1×1 conv; NHWC in and out.
- SafeUAV-Large (neural-wrappers model_unet_dilatedconv.py, mode dilate2_serial_concatenate): U-Net blocks of
  two conv+ReLU, 2×2 max-pool; six serial dilated convs concatenated; ConcatenateBlock = ReLU(convT k3 s2 p0),
  drop last row/column, cat([skip, up]) -- the skip channels come FIRST.
- EfficientNet-B5 'tf_' (gen-efficientnet-pytorch): TF 'same' padding computed from the input size, BN eps 1e-3,
  swish, SE reduced from the block input (swish, sigmoid gate); AdaBins taps stage outputs 0, 1, 2, 4 and
  conv_head before bn2.
- AdaBins head (shariqfarooq123/AdaBins miniViT.py, layers.py, unet_adaptive_bins.py): post-norm transformer
  (ReLU, sequence first), token 0 -> regressor, tokens 1..128 dotted per pixel with conv3x3(x); 'linear' norm;
  edges = cumsum([min, (max - min) * w]); depth = sum(softmax(conv_out) * centres).
"""
import math

import pytest

torch = pytest.importorskip("torch")
F = torch.nn.functional

from edge_landing.export.zoo import get_arch  # noqa: E402
from edge_landing.export.zoo.adabins import AdaBins  # noqa: E402
from edge_landing.export.zoo.efficientnet import EFFICIENTNET_B5_TF, EfficientNet  # noqa: E402
from edge_landing.runtime.perception.contract import Task  # noqa: E402

REL_TOL = 1e-3


# Keep torch to one thread in this module (tests/conftest.py).
pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).abs().max() / b.abs().max().clamp_min(1e-12))


def _randomise(module: torch.nn.Module, seed: int) -> None:
    """Non-trivial weights and BatchNorm statistics, so that every term of the function is exercised."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for _, p in module.named_parameters():
            fan_in = p[0].numel() if p.dim() > 1 else 1
            p.copy_(torch.randn(p.shape, generator=g) / math.sqrt(fan_in))
        for name, b in module.named_buffers():
            if name.endswith("running_mean"):
                b.copy_(0.1 * torch.randn(b.shape, generator=g))
            elif name.endswith("running_var"):
                b.copy_(0.5 + torch.rand(b.shape, generator=g))


# -- SafeUAV --------------------------------------------------------------------------------------------------
def _conv(x, w, b, stride=1, dilation=1):
    return F.conv2d(x, w, b, stride=stride, padding=dilation * (w.shape[-1] // 2), dilation=dilation)


def _safeuav_small_reference(x_nhwc, t):
    """``t``: the ordered tensor list of the authors' checkpoint (weight, bias per module, registration order)."""
    t = iter(t)
    nxt = lambda: (next(t), next(t))  # noqa: E731
    down1, down1pool, down2, down2pool, down3, down3pool = (nxt() for _ in range(6))
    dilate = [nxt() for _ in range(6)]
    up3_tr, up3, up2_tr, up2, up1_tr, up1, final = (nxt() for _ in range(7))
    x = x_nhwc.permute(0, 3, 1, 2)
    y1 = F.relu(_conv(x, *down1))
    y2 = F.relu(_conv(F.relu(_conv(y1, *down1pool, stride=2)), *down2))
    y3 = F.relu(_conv(F.relu(_conv(y2, *down2pool, stride=2)), *down3))
    y = F.relu(_conv(y3, *down3pool, stride=2))
    total = 0
    for (w, b), d in zip(dilate, (1, 2, 4, 8, 16, 32)):
        y = F.relu(_conv(y, w, b, dilation=d))
        total = total + y
    y = total
    for (tw, tb), (cw, cb), skip in ((up3_tr, up3, y3), (up2_tr, up2, y2), (up1_tr, up1, y1)):
        u = F.relu(F.conv_transpose2d(y, tw, tb, stride=2, padding=1))
        y = F.relu(_conv(F.pad(u, (0, 1, 0, 1)) + skip, cw, cb))
    return F.conv2d(y, *final).permute(0, 2, 3, 1)


def _safeuav_large_reference(x_nhwc, t):
    t = iter(t)
    nxt = lambda: (next(t), next(t))  # noqa: E731
    block = lambda x, c1, c2: F.relu(_conv(F.relu(_conv(x, *c1)), *c2))  # noqa: E731

    def concatenate_block(skip, x, convt):
        up = F.relu(F.conv_transpose2d(x, *convt, stride=2))[:, :, :-1, :-1]
        return torch.cat([skip, up], dim=1)

    down = [(nxt(), nxt()) for _ in range(3)]
    dilate = [nxt() for _ in range(6)]
    bottleneck_t = nxt()
    up_block3 = (nxt(), nxt())
    up2 = nxt()
    up_block2 = (nxt(), nxt())
    up1 = nxt()
    up_block1 = (nxt(), nxt())
    final = nxt()
    x = x_nhwc.permute(0, 3, 1, 2)
    d1 = block(x, *down[0])
    d2 = block(F.max_pool2d(d1, 2), *down[1])
    d3 = block(F.max_pool2d(d2, 2), *down[2])
    y, outs = F.max_pool2d(d3, 2), []
    for (w, b), d in zip(dilate, (1, 2, 4, 8, 16, 32)):
        y = F.relu(_conv(y, w, b, dilation=d))
        outs.append(y)
    y = block(concatenate_block(d3, torch.cat(outs, 1), bottleneck_t), *up_block3)
    y = block(concatenate_block(d2, y, up2), *up_block2)
    y = block(concatenate_block(d1, y, up1), *up_block1)
    return F.conv2d(y, *final).permute(0, 2, 3, 1)


@pytest.mark.parametrize("arch,reference", [("safeuav-small", _safeuav_small_reference),
                                            ("safeuav-large", _safeuav_large_reference)])
@pytest.mark.parametrize("task", [Task.HVO, Task.DEPTH])
def test_safeuav_matches_the_authors_definition(arch, reference, task):
    model = get_arch(arch).build(task).eval()
    _randomise(model, seed=3)
    ordered = [p.detach().clone() for p in model.parameters()]     # what the authors' .pkl holds
    x = torch.rand(2, 24, 40, 3, generator=torch.Generator().manual_seed(4))
    with torch.no_grad():
        (ours,) = model(x)
        ref = reference(x, ordered)
    assert ours.shape == ref.shape == (2, 24, 40, 3 if task is Task.HVO else 1)
    assert _rel_err(ours, ref) < REL_TOL


# -- EfficientNet-B5 (tf_ port) as AdaBins taps it ------------------------------------------------------------
STAGE_STRIDES = (1, 2, 2, 2, 1, 2, 1)       # EfficientNet-B0 table; only a stage's first block strides


def _tf_same_conv(x, w, stride, groups=1):
    k = w.shape[-1]
    pads = []
    for size in (x.shape[-1], x.shape[-2]):         # F.pad order: width first
        total = max((math.ceil(size / stride) - 1) * stride + k - size, 0)
        pads += [total // 2, total - total // 2]
    return F.conv2d(F.pad(x, pads), w, None, stride=stride, groups=groups)


def _bn(x, sd, prefix):
    return F.batch_norm(x, sd[prefix + ".running_mean"], sd[prefix + ".running_var"], sd[prefix + ".weight"],
                        sd[prefix + ".bias"], training=False, eps=1e-3)


def _se(x, sd, p):
    s = F.silu(F.conv2d(x.mean((2, 3), keepdim=True), sd[p + ".se.conv_reduce.weight"],
                        sd[p + ".se.conv_reduce.bias"]))
    return x * torch.sigmoid(F.conv2d(s, sd[p + ".se.conv_expand.weight"], sd[p + ".se.conv_expand.bias"]))


def _efficientnet_taps_reference(x, sd):
    x = F.silu(_bn(_tf_same_conv(x, sd["conv_stem.weight"], 2), sd, "bn1"))
    taps = []
    for s, stride0 in enumerate(STAGE_STRIDES):
        b = 0
        while f"blocks.{s}.{b}.conv_dw.weight" in sd:
            p, stride = f"blocks.{s}.{b}", (stride0 if b == 0 else 1)
            inp = x
            if p + ".conv_pwl.weight" in sd:        # inverted residual
                y = F.silu(_bn(F.conv2d(x, sd[p + ".conv_pw.weight"]), sd, p + ".bn1"))
                w = sd[p + ".conv_dw.weight"]
                y = _se(F.silu(_bn(_tf_same_conv(y, w, stride, groups=w.shape[0]), sd, p + ".bn2")), sd, p)
                y = _bn(F.conv2d(y, sd[p + ".conv_pwl.weight"]), sd, p + ".bn3")
            else:                                   # depthwise separable (stage 0)
                w = sd[p + ".conv_dw.weight"]
                y = _se(F.silu(_bn(_tf_same_conv(x, w, stride, groups=w.shape[0]), sd, p + ".bn1")), sd, p)
                y = _bn(F.conv2d(y, sd[p + ".conv_pw.weight"]), sd, p + ".bn2")
            x = y + inp if (stride == 1 and y.shape == inp.shape) else y
            b += 1
        taps.append(x)
    head = F.conv2d(x, sd["conv_head.weight"])      # AdaBins' bottleneck: before bn2 / act2
    return [taps[i] for i in (0, 1, 2, 4)] + [head]


def test_efficientnet_b5_taps_match_the_tf_port_at_an_odd_size():
    torch.manual_seed(5)
    net = EfficientNet(EFFICIENTNET_B5_TF).eval()
    _randomise(net, seed=6)
    sd = {k: v.detach() for k, v in net.state_dict().items()}
    x = torch.randn(1, 3, 45, 67, generator=torch.Generator().manual_seed(7))   # odd: asymmetric padding
    with torch.no_grad():
        feats = net.forward_features(x)
        ours = [feats[i] for i in (0, 1, 2, 4)] + [feats[-1]]
        ref = _efficientnet_taps_reference(x, sd)
    assert [t.shape[1] for t in ref] == [24, 40, 64, 176, 2048]
    for a, b in zip(ours, ref):
        assert a.shape == b.shape and _rel_err(a, b) < REL_TOL


# -- AdaBins head: mViT, conv_out and the bins ----------------------------------------------------------------
def _encoder_layer(x, sd, p, heads=4):
    """nn.TransformerEncoderLayer defaults: post-norm, ReLU, (S, N, E); eval so no dropout."""
    s, n, e = x.shape
    q, k, v = F.linear(x, sd[p + "self_attn.in_proj_weight"], sd[p + "self_attn.in_proj_bias"]).chunk(3, -1)
    split = lambda t: t.reshape(s, n * heads, e // heads).transpose(0, 1)  # noqa: E731
    att = torch.softmax(split(q) @ split(k).transpose(1, 2) / math.sqrt(e // heads), -1) @ split(v)
    att = F.linear(att.transpose(0, 1).reshape(s, n, e), sd[p + "self_attn.out_proj.weight"],
                   sd[p + "self_attn.out_proj.bias"])
    x = F.layer_norm(x + att, (e,), sd[p + "norm1.weight"], sd[p + "norm1.bias"])
    ff = F.linear(F.relu(F.linear(x, sd[p + "linear1.weight"], sd[p + "linear1.bias"])),
                  sd[p + "linear2.weight"], sd[p + "linear2.bias"])
    return F.layer_norm(x + ff, (e,), sd[p + "norm2.weight"], sd[p + "norm2.bias"])


def _adabins_head_reference(x, sd, min_val, max_val):
    a = "adaptive_bins_layer."
    pt = a + "patch_transformer."
    emb = F.conv2d(x, sd[pt + "embedding_convPxP.weight"], sd[pt + "embedding_convPxP.bias"], stride=16).flatten(2)
    emb = emb + sd[pt + "positional_encodings"][:emb.shape[2]].T.unsqueeze(0)
    tgt = emb.permute(2, 0, 1)
    for i in range(4):
        tgt = _encoder_layer(tgt, sd, f"{pt}transformer_encoder.layers.{i}.")
    feats = F.conv2d(x, sd[a + "conv3x3.weight"], sd[a + "conv3x3.bias"], padding=1)
    n, c, h, w = feats.shape
    queries = tgt[1:129].permute(1, 0, 2)                                          # N, 128, E
    maps = torch.einsum("nqe,nep->nqp", queries, feats.reshape(n, c, h * w)).reshape(n, 128, h, w)
    r = tgt[0]
    for i in (0, 2):
        r = F.leaky_relu(F.linear(r, sd[f"{a}regressor.{i}.weight"], sd[f"{a}regressor.{i}.bias"]), 0.01)
    r = torch.relu(F.linear(r, sd[a + "regressor.4.weight"], sd[a + "regressor.4.bias"])) + 0.1
    widths = (max_val - min_val) * r / r.sum(1, keepdim=True)
    edges = torch.cumsum(torch.cat([torch.full_like(widths[:, :1], min_val), widths], 1), 1)
    centres = 0.5 * (edges[:, :-1] + edges[:, 1:])
    probs = torch.softmax(F.conv2d(maps, sd["conv_out.0.weight"], sd["conv_out.0.bias"]), 1)
    return edges, (probs * centres[:, :, None, None]).sum(1, keepdim=True)


@pytest.mark.parametrize("bins,max_depth", [(80, 10.0), (256, 80.0)])
def test_adabins_head_matches_the_authors_definition(bins, max_depth):
    # Only the head is under test: build on the meta device (no memory), drop the encoder/decoder, materialise.
    with torch.device("meta"):
        model = AdaBins(bins=bins, min_depth=1e-3, max_depth=max_depth)
    model.encoder, model.decoder = torch.nn.Identity(), torch.nn.Identity()
    model = model.to_empty(device="cpu").eval()
    _randomise(model, seed=8)
    sd = {k: v.detach() for k, v in model.state_dict().items()}
    x = torch.randn(2, 128, 176, 192, generator=torch.Generator().manual_seed(9))   # 11×12 = 132 patches
    with torch.no_grad():
        edges, depth = model(x)
        ref_edges, ref_depth = _adabins_head_reference(x, sd, 1e-3, max_depth)
    assert edges.shape == (2, bins + 1) and depth.shape == (2, 1, 176, 192)
    assert _rel_err(edges, ref_edges) < REL_TOL and _rel_err(depth, ref_depth) < REL_TOL


# -- DenseDepth (ialhashim/DenseDepth PyTorch/model.py on torchvision's densenet169) ------------------------
def _bn5(x, sd, prefix):
    return F.batch_norm(x, sd[prefix + ".running_mean"], sd[prefix + ".running_var"], sd[prefix + ".weight"],
                        sd[prefix + ".bias"], training=False, eps=1e-5)


def _densedepth_reference(x, sd):
    """The authors' encoder lists every ``features`` module output; the decoder reads items 3, 4, 6, 8, 12
    (relu0, pool0, transition1, transition2, norm5) and starts with conv2(relu(norm5))."""
    e = "encoder.original_model.features."
    feats = [x]
    y = F.conv2d(x, sd[e + "conv0.weight"], stride=2, padding=3)
    feats.append(y)
    y = _bn5(y, sd, e + "norm0")
    feats.append(y)
    feats.append(F.relu(y))                                            # relu0
    feats.append(F.max_pool2d(feats[-1], 3, stride=2, padding=1))      # pool0
    y = feats[-1]
    for blk in range(1, 5):
        k = 1
        while f"{e}denseblock{blk}.denselayer{k}.conv1.weight" in sd:
            p = f"{e}denseblock{blk}.denselayer{k}."
            h = F.conv2d(F.relu(_bn5(y, sd, p + "norm1")), sd[p + "conv1.weight"])
            h = F.conv2d(F.relu(_bn5(h, sd, p + "norm2")), sd[p + "conv2.weight"], padding=1)
            y = torch.cat([y, h], 1)
            k += 1
        feats.append(y)
        if blk < 4:
            p = f"{e}transition{blk}."
            y = F.avg_pool2d(F.conv2d(F.relu(_bn5(y, sd, p + "norm")), sd[p + "conv.weight"]), 2, stride=2)
            feats.append(y)
    feats.append(_bn5(y, sd, e + "norm5"))
    d = "decoder."
    x_d = F.conv2d(F.relu(feats[12]), sd[d + "conv2.weight"], sd[d + "conv2.bias"])
    for i, skip in zip(range(1, 5), (feats[8], feats[6], feats[4], feats[3])):
        up = F.interpolate(x_d, size=skip.shape[2:], mode="bilinear", align_corners=True)
        h = F.conv2d(torch.cat([up, skip], 1), sd[f"{d}up{i}.convA.weight"], sd[f"{d}up{i}.convA.bias"], padding=1)
        x_d = F.leaky_relu(F.conv2d(h, sd[f"{d}up{i}.convB.weight"], sd[f"{d}up{i}.convB.bias"], padding=1), 0.2)
    return F.conv2d(x_d, sd[d + "conv3.weight"], sd[d + "conv3.bias"], padding=1)


def test_densedepth_matches_the_authors_definition():
    torch.manual_seed(10)
    model = get_arch("densedepth").build(Task.DEPTH).eval()
    _randomise(model, seed=11)
    sd = {k: v.detach() for k, v in model.state_dict().items()}
    x = torch.rand(1, 3, 64, 96, generator=torch.Generator().manual_seed(12))
    with torch.no_grad():
        (ours,) = model(x)
        ref = _densedepth_reference(x, sd)
    assert ours.shape == ref.shape == (1, 1, 32, 48)
    assert _rel_err(ours, ref) < REL_TOL
