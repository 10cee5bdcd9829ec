import dataclasses

import pytest
import torch

from poseflow.models import DiTOverrides, FunFlow6DNet, NetConfig, NetInputs

CFG = NetConfig(
    geometric_dim=6, semantic_dim=5, feature_dim=8, fusion_heads=2, posenc_dim=8, dit_preset="tiny"
)


def _inputs(B=2, n=5, seed=0):
    """Network inputs and a noise sample ``x_0``."""
    g = torch.Generator().manual_seed(seed)
    L = 2 * n
    inputs = NetInputs(
        geometric=torch.randn(B, L, 6, generator=g),
        semantic=torch.randn(B, L, 5, generator=g),
        points=torch.randn(B, L, 3, generator=g),
        normals=torch.randn(B, L, 3, generator=g),
    )
    return inputs, torch.randn(B, L, 3, generator=g)


def test_fusion_keeps_query_and_target_apart():
    torch.manual_seed(0)
    net = FunFlow6DNet(CFG).eval()
    a, x_0 = _inputs()
    b = dataclasses.replace(a, semantic=a.semantic.clone())
    b.semantic[:, 5:] += 1.0  # change only the target's appearance
    ca, cb = net.condition(a, x_0=x_0), net.condition(b, x_0=x_0)
    assert torch.allclose(ca[:, :5], cb[:, :5], atol=1e-6)
    assert not torch.allclose(ca[:, 5:], cb[:, 5:], atol=1e-3)


def test_padding_does_not_change_valid_points():
    torch.manual_seed(0)
    net = FunFlow6DNet(CFG).eval()
    for p in net.dit.parameters():  # leave the adaLN-Zero identity so outputs depend on inputs
        torch.nn.init.normal_(p, std=0.05)
    a, x_0 = _inputs()
    mask = torch.ones(2, 10, dtype=torch.bool)
    mask[:, 8:] = False
    a.mask = mask
    b = NetInputs.from_kwargs({k: v.clone() for k, v in a.net_kwargs().items()})
    x_0b = x_0.clone()
    for v in (b.geometric, b.semantic, b.points, b.normals, x_0b):
        v[:, 8:] = 7.0
    x, t = torch.randn(2, 10, 3), torch.rand(2)
    va = net(x=x, t=t, inputs=a, x_0=x_0)
    vb = net(x=torch.where(mask[..., None], x, 3.0), t=t, inputs=b, x_0=x_0b)
    assert torch.allclose(va[:, :8], vb[:, :8], atol=1e-5)
    assert (vb[:, 8:] == 0).all()


def test_gradients_reach_every_parameter():
    torch.manual_seed(0)
    net = FunFlow6DNet(CFG)
    for p in net.dit.parameters():
        torch.nn.init.normal_(p, std=0.05)
    inputs, x_0 = _inputs()
    v = net(x=torch.randn(2, 10, 3), t=torch.rand(2), inputs=inputs, x_0=x_0)
    v.square().sum().backward()
    missing = [n for n, p in net.named_parameters() if p.grad is None or not p.grad.abs().sum()]
    assert not missing


def test_dit_preset_fields_can_be_overridden():
    net = FunFlow6DNet(dataclasses.replace(CFG, dit=DiTOverrides(hidden_dim=48, depth=3)))
    assert net.dit.config.hidden_dim == 48 and len(net.dit.blocks) == 3
    assert net.dit.config.cond_dim == CFG.feature_dim + CFG.posenc_dim


@pytest.mark.parametrize("fusion", ["gated", "cross", "concat_mlp", "sum"])
def test_autocast_with_one_identity_adapter(fusion):
    # semantic_dim == feature_dim: an Identity adapter next to a Linear one, as in training on
    # CUDA under bf16 autocast (run here on the CPU's autocast).
    cfg = NetConfig(
        geometric_dim=6, semantic_dim=8, feature_dim=8, fusion=fusion, fusion_heads=2,
        posenc_dim=8, dit_preset="tiny",
    )  # fmt: skip
    inputs, x_0 = _inputs()
    inputs.semantic = torch.randn(2, 10, 8)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        v = FunFlow6DNet(cfg)(x=torch.randn(2, 10, 3), t=torch.rand(2), inputs=inputs, x_0=x_0)
    assert v.shape == (2, 10, 3) and torch.isfinite(v).all()


@pytest.mark.parametrize("noise_conditioning", [False, True])
def test_samples_per_instance_equal_sampling_the_repeated_instances(noise_conditioning):
    from poseflow.flows.samplers import get_sampler

    torch.manual_seed(0)
    net = FunFlow6DNet(dataclasses.replace(CFG, noise_conditioning=noise_conditioning)).eval()
    for p in net.parameters():
        torch.nn.init.normal_(p, std=0.1)
    inputs, _ = _inputs()
    inputs.mask = torch.ones(2, 10, dtype=torch.bool)
    inputs.mask[1, 8:] = False
    frozen = torch.zeros(2, 10, dtype=torch.bool)
    frozen[:, :5] = True
    anchor = torch.where(frozen[..., None], inputs.points, 0.0)
    sampler = get_sampler("euler", steps=3)
    once = net.sample(inputs, sampler, frozen_mask=frozen, x_frozen=anchor, num_samples=3,
                      generator=torch.Generator().manual_seed(1))  # fmt: skip
    rep = inputs.repeat_interleave(3)
    every = net.sample(rep, sampler, frozen_mask=frozen.repeat_interleave(3, 0),
                       x_frozen=anchor.repeat_interleave(3, 0),
                       generator=torch.Generator().manual_seed(1))  # fmt: skip
    assert once.shape == (6, 10, 3)
    torch.testing.assert_close(once, every, rtol=0, atol=1e-5)
    assert not torch.allclose(once[0], once[1])  # each sample has its own noise
    with pytest.raises(ValueError):
        net.sample(inputs, sampler, frozen_mask=frozen, num_samples=0)


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_sampling_in_a_lower_precision_stays_close_and_integrates_in_the_inputs_dtype(precision):
    from poseflow.flows.samplers import get_sampler

    torch.manual_seed(0)
    net = FunFlow6DNet(CFG).eval()
    for p in net.parameters():
        torch.nn.init.normal_(p, std=0.1)
    inputs, _ = _inputs()
    frozen = torch.zeros(2, 10, dtype=torch.bool)
    frozen[:, :5] = True
    anchor = torch.where(frozen[..., None], inputs.points, 0.0)

    def run(name):
        return net.sample(inputs, get_sampler("midpoint", steps=2), frozen_mask=frozen,
                          x_frozen=anchor, num_samples=2, precision=name,
                          generator=torch.Generator().manual_seed(3))  # fmt: skip

    reference, out = run("fp32"), run(precision)
    assert out.dtype == torch.float32
    assert torch.equal(
        out[frozen.repeat_interleave(2, 0)], reference[frozen.repeat_interleave(2, 0)]
    )
    atol = 0 if precision == "fp32" else 0.05 * float(reference.abs().max())
    torch.testing.assert_close(out, reference, rtol=0, atol=atol)
    assert torch.equal(out, reference) == (precision == "fp32")  # bf16 did run in bf16
    with pytest.raises(ValueError, match="precision"):
        run("fp8")


@pytest.mark.parametrize("pinned", [True, False])
@pytest.mark.parametrize("noise_conditioning", [False, True])
def test_sampling_uses_the_dits_fixed_query_shortcuts_without_changing_samples(
    pinned, noise_conditioning
):
    """A pinned anchor is run once per instance and its velocity never computed; same samples."""
    from poseflow.flows.samplers import get_sampler

    torch.manual_seed(0)
    cfg = dataclasses.replace(CFG, noise_conditioning=noise_conditioning)
    net = FunFlow6DNet(cfg).double().eval()
    for p in net.parameters():
        torch.nn.init.normal_(p, std=0.2)
    inputs, _ = _inputs(B=3)
    inputs = NetInputs(**{f: getattr(inputs, f).double() for f in NetInputs.field_names()[:4]})
    inputs.mask = torch.ones(3, 10, dtype=torch.bool)
    inputs.mask[1, 2] = inputs.mask[2, 7:] = False
    frozen = torch.zeros(3, 10, dtype=torch.bool)
    frozen[:, :5] = True
    anchor = torch.where(frozen[..., None], inputs.points, 0.0) if pinned else None
    seen = []
    forward = net.dit.forward

    def recorded(x, t, *, frozen_query=False, query_repeats=1, **cond):
        seen.append((frozen_query, query_repeats))
        return forward(x, t, frozen_query=frozen_query, query_repeats=query_repeats, **cond)

    def plain_forward(x, t, *, frozen_query=False, query_repeats=1, **cond):
        return forward(x, t, **cond)

    def run():
        return net.sample(inputs, get_sampler("midpoint", steps=2), frozen_mask=frozen,
                          x_frozen=anchor, num_samples=4,
                          generator=torch.Generator().manual_seed(2))  # fmt: skip

    net.dit.forward = recorded
    fast = run()
    net.dit.forward = plain_forward
    plain = run()
    assert seen == [(True, 4 if pinned and not noise_conditioning else 1)] * 4
    torch.testing.assert_close(fast, plain, rtol=0, atol=1e-12)
