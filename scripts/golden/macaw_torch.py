"""MACAW (Mitchell et al., ICML 2021) in functional PyTorch, written from
../shared/reference/macaw.md (sections 3, 4, 5 and the pseudo-code of section 6), which was checked
there against the official code with `higher` to ~1e-15 in float64.

It is the reference the Rust implementation (crates/macaw) is compared with, operation for
operation: the same ops in the same order, so that on one CPU with one thread the two agree bit for
bit (scripts/golden/make_macaw_fixtures.py, crates/macaw/tests/it/parity.rs), and the PyTorch side of
`promptdt bench` (scripts/bench/macaw_bench.py).

Parameters are plain tensors (no nn.Module), in the official order: per WLinear layer
[z, fc.weight, fc.bias]; the value net has layers fc_0..fc_3, the policy fc_0..fc_3 then the
advantage head head_0, head_1. The per-tensor learned inner learning rates are one vector per net
(rho_v [12], rho_pi [18]); Adam is elementwise, so this equals the official list of scalars (the
head entries get a zero gradient where the official ones get none: Adam moves neither).
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

LATENT = 100  # hard-coded in the official nn.py
HEAD = 32  # policy_head = [32, 1]


def layer_dims(obs_dim, act_dim, width, depth=3):
    """(value layers, policy layers) as lists of (in, out); the policy's last two are the head."""
    trunk = [obs_dim] + [width] * depth
    value = list(zip(trunk, trunk[1:] + [1]))
    policy = list(zip(trunk, trunk[1:] + [act_dim])) + [(width + act_dim, HEAD), (HEAD, 1)]
    return value, policy


def param_names(net, n_layers):
    out = []
    for i in range(n_layers):
        tag = f"fc_{i}" if net == "value" or i < n_layers - 2 else f"head_{i - (n_layers - 2)}"
        out += [f"{net}.{tag}.z", f"{net}.{tag}.weight", f"{net}.{tag}.bias"]
    return out


def init_params(dims, gen, dtype):
    """WLinear init: z ~ N(0, (1/out)^2); generator Linear(100, in*out+out) with PyTorch's default
    U(-1/sqrt(100), 1/sqrt(100)) for weight and bias."""
    ps = []
    bound = 1.0 / math.sqrt(LATENT)
    for n_in, n_out in dims:
        rows = n_in * n_out + n_out
        z = torch.randn(LATENT, generator=gen, dtype=torch.float64) / n_out
        w = (torch.rand(rows, LATENT, generator=gen, dtype=torch.float64) * 2 - 1) * bound
        b = (torch.rand(rows, generator=gen, dtype=torch.float64) * 2 - 1) * bound
        ps += [z.to(dtype), w.to(dtype), b.to(dtype)]
    return ps


def wlinear(x, z, w, b, n_in, n_out):
    theta = F.linear(z, w, b)  # [in*out + out]
    m = theta[: n_in * n_out].view(n_in, n_out)  # input index major
    return x @ m + theta[n_in * n_out:]


def act(x, hidden):
    return torch.relu(x) if hidden == "relu" else torch.tanh(x)


def value_forward(ps, dims, s, hidden="relu"):
    x = s
    for i, (n_in, n_out) in enumerate(dims):
        if i > 0:
            x = act(x, hidden)
        x = wlinear(x, ps[3 * i], ps[3 * i + 1], ps[3 * i + 2], n_in, n_out)
    return x  # [B, 1]


def policy_forward(ps, dims, s, a=None, hidden="relu"):
    """mu [B, A] (and the advantage head's prediction [B, 1] when a is given)."""
    n_trunk = len(dims) - 2
    x = s
    for i in range(n_trunk - 1):  # pre-activation h after fc_{depth-1}
        if i > 0:
            x = act(x, hidden)
        n_in, n_out = dims[i]
        x = wlinear(x, ps[3 * i], ps[3 * i + 1], ps[3 * i + 2], n_in, n_out)
    h = x
    j = n_trunk - 1
    mu = torch.tanh(wlinear(act(h, hidden), ps[3 * j], ps[3 * j + 1], ps[3 * j + 2], *dims[j]))
    if a is None:
        return mu, None
    # Official quirk: the activation is applied to the concatenation, actions included.
    y = act(torch.cat([h, a], -1), hidden)
    k = n_trunk
    y = wlinear(y, ps[3 * k], ps[3 * k + 1], ps[3 * k + 2], *dims[k])
    y = act(y, hidden)
    y = wlinear(y, ps[3 * k + 3], ps[3 * k + 4], ps[3 * k + 5], *dims[k + 1])
    return mu, y


class Hyper:
    sigma = 0.2
    adv_clip = 20.0
    temp = 1.0
    target_alpha = 0.9
    hidden = "relu"


def value_loss(ps, dims, batch, target=None, hp=Hyper):
    """Inner (target None): MC targets G; outer: G + kappa * V_target(s_T)."""
    with torch.no_grad():
        if target is None:
            ret = batch["mc_return"]
        else:
            ret = batch["mc_return"] + batch["terminal_discount"] * value_forward(
                target, dims, batch["terminal_obs"], hp.hidden)
    v = value_forward(ps, dims, batch["obs"], hp.hidden)
    return (v - ret).pow(2).mean()


def advantages(vps, vdims, batch, hp=Hyper):
    """A (raw) and the AWR weights, without gradient."""
    with torch.no_grad():
        est = batch["mc_return"] + batch["terminal_discount"] * value_forward(
            vps, vdims, batch["terminal_obs"], hp.hidden)
        adv = (est - value_forward(vps, vdims, batch["obs"], hp.hidden)).squeeze(-1)  # [B]
        norm = (adv - adv.mean()) / adv.std() / hp.temp  # unbiased std
        weights = norm.clamp(max=math.log(hp.adv_clip)).exp()
    return adv, weights


def policy_loss(ps, dims, vps, vdims, batch, rho_adv, inner, hp=Hyper):
    adv, weights = advantages(vps, vdims, batch, hp)
    a = batch["act"]
    mu, adv_pred = policy_forward(ps, dims, batch["obs"], a if inner else None, hp.hidden)
    # torch.distributions.Normal(mu, sigma).log_prob(a), summed over action dims
    var = hp.sigma ** 2
    log_prob = -((a - mu) ** 2) / (2 * var) - math.log(hp.sigma) - math.log(math.sqrt(2 * math.pi))
    losses = -(log_prob.sum(-1) * weights)
    if inner:
        losses = losses + F.softplus(rho_adv) * (adv_pred.squeeze(-1) - adv) ** 2
    return losses.mean()


def sgd(ps, loss, rho, create_graph):
    grads = torch.autograd.grad(loss, ps, create_graph=create_graph)
    lrs = F.softplus(rho)
    return [p - lrs[i] * g for i, (p, g) in enumerate(zip(ps, grads))]


def meta_task(vps, pps, rho_v, rho_pi, rho_adv, vdims, pdims, d_in, d_out, n_train, hp=Hyper):
    """One task of a meta-training step: accumulates into the leaves' .grad; returns the losses
    and the adapted parameters."""
    l_v_in = value_loss(vps, vdims, d_in, None, hp)
    vps2 = sgd(vps, l_v_in, rho_v, True)
    with torch.no_grad():
        target = [p * hp.target_alpha + q * (1 - hp.target_alpha) for p, q in zip(vps, vps2)]
    l_v_out = value_loss(vps2, vdims, d_out, target, hp)
    (l_v_out / n_train).backward()
    vps2 = [p.detach() for p in vps2]
    l_p_in = policy_loss(pps, pdims, vps2, vdims, d_in, rho_adv, True, hp)
    pps2 = sgd(pps, l_p_in, rho_pi, True)
    l_p_out = policy_loss(pps2, pdims, vps2, vdims, d_out, rho_adv, False, hp)
    (l_p_out / n_train).backward()
    return {"value_inner_loss": l_v_in.detach(), "value_outer_loss": l_v_out.detach(),
            "policy_inner_loss": l_p_in.detach(), "policy_outer_loss": l_p_out.detach()}, \
        vps2, [p.detach() for p in pps2]


def adapt(vps, pps, rho_v, rho_pi, rho_adv, vdims, pdims, batch, steps, hp=Hyper):
    """Test-time adaptation: `steps` value steps (MC targets), then `steps` policy steps against
    the adapted value function; plain SGD with the learned learning rates, no second order."""
    v = [p.detach().requires_grad_() for p in vps]
    for _ in range(steps):
        v = [p.detach().requires_grad_() for p in sgd(v, value_loss(v, vdims, batch, None, hp),
                                                       rho_v.detach(), False)]
    v = [p.detach() for p in v]
    pi = [p.detach().requires_grad_() for p in pps]
    for _ in range(steps):
        loss = policy_loss(pi, pdims, v, vdims, batch, rho_adv.detach(), True, hp)
        pi = [p.detach().requires_grad_() for p in sgd(pi, loss, rho_pi.detach(), False)]
    return v, [p.detach() for p in pi]
