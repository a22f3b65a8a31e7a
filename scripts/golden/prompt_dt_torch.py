"""Prompt-DT reference model in PyTorch, written from shared/reference/promptdt-reference.md (a), (c.2).

This module is the Python side of the Rust/PyTorch parity test (crates/train/tests/it/parity.rs) and of the
speed benchmark (scripts/bench/bench_torch.py). It follows the op sequence of the reference
(HF transformers 4.5.1 GPT-2 without position embedding + the Prompt-DT wrapper) op for op, because the
Rust side mirrors the same ATen calls and we want bitwise agreement. Do not "simplify" an expression here
(e.g. `x / c` into `x * (1 / c)`, `nn.Linear` into a matmul, or reorder dropouts): it changes the bits.

ATen ops per module, for whoever mirrors this (all of them come from libtorch_cpu, so the same library
gives the same bits when called with the same shapes, strides and scalars):
  nn.Linear          -> at::linear(x, W, b)  (3-D contiguous input: addmm on the flattened input;
                        non-contiguous input, e.g. x[:, 1] below: matmul then add_)
  Conv1D             -> at::addmm(b, x.view(-1, in), W).view(..., out)
  nn.Embedding       -> at::embedding
  nn.LayerNorm       -> at::layer_norm(x, [H], w, b, 1e-5)
  nn.Dropout(p=0.1)  -> at::dropout(x, 0.1, train)  (CPU: bernoulli_(0.9) mask, div_(0.9), mul)
  softmax            -> at::softmax(w, -1)

Deliberate deviations from the official code (documented in the reference's pitfalls h.6 / h.7):
  * no special branch for 3*Lp == 3*K (the official code then reshapes all prompts of the batch into one
    row and repeats it B times); the prompt is always concatenated per sample;
  * no `% 10 == 1` hack that drops the last prompt rtg entry.
The prompt tuple has 6 entries (states, actions, rewards, returns_to_go, timesteps, attention_mask):
the official 7-tuple also carries `dones`, which the model never reads.
"""
from __future__ import annotations

import torch
from torch import nn

# Reference hyper-parameters (pdt_main.py + GPT2Config 4.5.1 defaults).
HIDDEN = 128
N_LAYER = 3
N_HEAD = 1
N_INNER = 4 * HIDDEN
N_CTX = 1024
MAX_EP_LEN = 1000
PDROP = 0.1  # resid_pdrop = attn_pdrop = embd_pdrop
LN_EPS = 1e-5
INIT_STD = 0.02

LR = 1e-4
WEIGHT_DECAY = 1e-4
WARMUP_STEPS = 10000
GRAD_CLIP = 0.25


class Conv1D(nn.Module):
    """HF GPT-2 Conv1D: a linear layer with the weight stored as (in, out)."""

    def __init__(self, nf: int, nx: int):
        super().__init__()
        self.nf = nf
        w = torch.empty(nx, nf)
        nn.init.normal_(w, std=INIT_STD)
        self.weight = nn.Parameter(w)
        self.bias = nn.Parameter(torch.zeros(nf))

    def forward(self, x):
        size_out = x.size()[:-1] + (self.nf,)
        x = torch.addmm(self.bias, x.view(-1, x.size(-1)), self.weight)
        return x.view(*size_out)


class Attention(nn.Module):
    def __init__(self, nx: int, n_ctx: int, n_head: int):
        super().__init__()
        assert nx % n_head == 0
        self.register_buffer(
            "bias", torch.tril(torch.ones((n_ctx, n_ctx), dtype=torch.uint8)).view(1, 1, n_ctx, n_ctx)
        )
        self.register_buffer("masked_bias", torch.tensor(-1e4))
        self.n_head = n_head
        self.split_size = nx
        self.c_attn = Conv1D(3 * nx, nx)
        self.c_proj = Conv1D(nx, nx)
        self.attn_dropout = nn.Dropout(PDROP)
        self.resid_dropout = nn.Dropout(PDROP)

    def split_heads(self, x, k: bool = False):
        x = x.view(*x.size()[:-1], self.n_head, x.size(-1) // self.n_head)
        return x.permute(0, 2, 3, 1) if k else x.permute(0, 2, 1, 3)

    def merge_heads(self, x):
        x = x.permute(0, 2, 1, 3).contiguous()
        return x.view(*x.size()[:-2], x.size(-2) * x.size(-1))

    def _attn(self, q, k, v, attention_mask):
        w = torch.matmul(q, k)
        w = w / (float(v.size(-1)) ** 0.5)
        nd, ns = w.size(-2), w.size(-1)
        mask = self.bias[:, :, ns - nd : ns, :ns]
        w = torch.where(mask.bool(), w, self.masked_bias.to(w.dtype))
        if attention_mask is not None:
            w = w + attention_mask
        w = torch.softmax(w, dim=-1)
        w = self.attn_dropout(w)
        return torch.matmul(w, v)

    def forward(self, h, attention_mask):
        x = self.c_attn(h)
        query, key, value = x.split(self.split_size, dim=2)
        query = self.split_heads(query)
        key = self.split_heads(key, k=True)
        value = self.split_heads(value)
        a = self._attn(query, key, value, attention_mask)
        a = self.merge_heads(a)
        a = self.c_proj(a)
        return self.resid_dropout(a)


class MLP(nn.Module):
    def __init__(self, n_state: int, nx: int):
        super().__init__()
        self.c_fc = Conv1D(n_state, nx)
        self.c_proj = Conv1D(nx, n_state)
        self.dropout = nn.Dropout(PDROP)

    def forward(self, x):
        h = torch.relu(self.c_fc(x))
        return self.dropout(self.c_proj(h))


class Block(nn.Module):
    def __init__(self, nx: int, n_ctx: int, n_head: int, n_inner: int):
        super().__init__()
        self.ln_1 = nn.LayerNorm(nx, eps=LN_EPS)
        self.attn = Attention(nx, n_ctx, n_head)
        self.ln_2 = nn.LayerNorm(nx, eps=LN_EPS)
        self.mlp = MLP(n_inner, nx)

    def forward(self, x, attention_mask):
        h = self.attn(self.ln_1(x), attention_mask) + x
        return h + self.mlp(self.ln_2(h))


class GPT2Model(nn.Module):
    """trajectory_gpt2.GPT2Model: HF 4.5.1 GPT-2 with the position embedding removed."""

    def __init__(self, n_embd=HIDDEN, n_layer=N_LAYER, n_head=N_HEAD, n_inner=N_INNER, n_ctx=N_CTX):
        super().__init__()
        self.wte = nn.Embedding(1, n_embd)  # vocab_size=1, never used
        self.drop = nn.Dropout(PDROP)
        self.h = nn.ModuleList([Block(n_embd, n_ctx, n_head, n_inner) for _ in range(n_layer)])
        self.ln_f = nn.LayerNorm(n_embd, eps=LN_EPS)
        self.apply(self._init_weights)  # GPT2PreTrainedModel.init_weights (post-order, like HF)

    @staticmethod
    def _init_weights(module):
        if isinstance(module, (nn.Linear, Conv1D)):
            module.weight.data.normal_(mean=0.0, std=INIT_STD)
            if module.bias is not None:
                module.bias.data.zero_()
        elif isinstance(module, nn.Embedding):
            module.weight.data.normal_(mean=0.0, std=INIT_STD)
        elif isinstance(module, nn.LayerNorm):
            module.bias.data.zero_()
            module.weight.data.fill_(1.0)

    def forward(self, inputs_embeds, attention_mask):
        batch_size = inputs_embeds.shape[0]
        attention_mask = attention_mask.view(batch_size, -1)
        attention_mask = attention_mask[:, None, None, :]
        attention_mask = attention_mask.to(dtype=inputs_embeds.dtype)
        attention_mask = (1.0 - attention_mask) * -10000.0
        hidden_states = self.drop(inputs_embeds)
        for block in self.h:
            hidden_states = block(hidden_states, attention_mask)
        return self.ln_f(hidden_states)


class PromptDecisionTransformer(nn.Module):
    def __init__(self, state_dim: int, act_dim: int, hidden_size: int = HIDDEN, max_ep_len: int = MAX_EP_LEN):
        super().__init__()
        self.state_dim, self.act_dim, self.hidden_size = state_dim, act_dim, hidden_size
        # Same construction order as the official code (matters only for the init RNG stream).
        self.transformer = GPT2Model(n_embd=hidden_size)

        self.embed_timestep = nn.Embedding(max_ep_len, hidden_size)
        self.embed_return = nn.Linear(1, hidden_size)
        self.embed_state = nn.Linear(state_dim, hidden_size)
        self.embed_action = nn.Linear(act_dim, hidden_size)

        self.prompt_embed_timestep = nn.Embedding(max_ep_len, hidden_size)
        self.prompt_embed_return = nn.Linear(1, hidden_size)
        self.prompt_embed_state = nn.Linear(state_dim, hidden_size)
        self.prompt_embed_action = nn.Linear(act_dim, hidden_size)

        self.embed_ln = nn.LayerNorm(hidden_size)

        self.predict_state = nn.Linear(hidden_size, state_dim)
        self.predict_action = nn.Sequential(nn.Linear(hidden_size, act_dim), nn.Tanh())
        self.predict_return = nn.Linear(hidden_size, 1)

    def _stack(self, embed_timestep, embed_return, embed_state, embed_action,
               states, actions, returns_to_go, timesteps, attention_mask):
        b, t = states.shape[0], states.shape[1]
        time_embeddings = embed_timestep(timesteps)
        state_embeddings = embed_state(states) + time_embeddings
        action_embeddings = embed_action(actions) + time_embeddings
        returns_embeddings = embed_return(returns_to_go) + time_embeddings
        stacked = torch.stack((returns_embeddings, state_embeddings, action_embeddings), dim=1)
        stacked = stacked.permute(0, 2, 1, 3).reshape(b, 3 * t, self.hidden_size)
        mask = torch.stack((attention_mask, attention_mask, attention_mask), dim=1)
        mask = mask.permute(0, 2, 1).reshape(b, 3 * t)
        return stacked, mask

    def forward(self, states, actions, rewards, returns_to_go, timesteps, attention_mask, prompt=None):
        """Returns (state_preds, action_preds, return_preds), each over the last K (history) steps.

        `rewards` (and the prompt's rewards) are accepted and unused, as in the reference.
        """
        batch_size, seq_length = states.shape[0], states.shape[1]
        stacked_inputs, stacked_mask = self._stack(
            self.embed_timestep, self.embed_return, self.embed_state, self.embed_action,
            states, actions, returns_to_go, timesteps, attention_mask)
        stacked_inputs = self.embed_ln(stacked_inputs)

        if prompt is not None:
            p_states, p_actions, _p_rewards, p_returns_to_go, p_timesteps, p_attention_mask = prompt
            p_stacked, p_mask = self._stack(
                self.prompt_embed_timestep, self.prompt_embed_return, self.prompt_embed_state,
                self.prompt_embed_action, p_states, p_actions, p_returns_to_go, p_timesteps, p_attention_mask)
            # no embed_ln on the prompt tokens (reference a.3 step 4)
            stacked_inputs = torch.cat((p_stacked, stacked_inputs), dim=1)
            stacked_mask = torch.cat((p_mask, stacked_mask), dim=1)

        x = self.transformer(stacked_inputs, stacked_mask)
        x = x.reshape(batch_size, -1, 3, self.hidden_size).permute(0, 2, 1, 3)

        return_preds = self.predict_return(x[:, 2])[:, -seq_length:, :]
        state_preds = self.predict_state(x[:, 2])[:, -seq_length:, :]
        action_preds = self.predict_action(x[:, 1])[:, -seq_length:, :]
        return state_preds, action_preds, return_preds


def masked_action_loss(action_preds, action_target, attention_mask):
    """Reference train_step_mix: MSE over the valid (mask > 0) history steps only."""
    act_dim = action_preds.shape[2]
    keep = attention_mask.reshape(-1) > 0
    ap = action_preds.reshape(-1, act_dim)[keep]
    at = action_target.reshape(-1, act_dim)[keep]
    return torch.mean((ap - at) ** 2)


def lr_lambda(step: int) -> float:
    return min((step + 1) / WARMUP_STEPS, 1)


def make_optimizer(model: nn.Module):
    """AdamW(lr 1e-4, wd 1e-4, defaults otherwise) + LambdaLR linear warm-up, as in the reference."""
    opt = torch.optim.AdamW(model.parameters(), lr=LR, weight_decay=WEIGHT_DECAY)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lr_lambda)
    return opt, sched


def adamw_uses_single_tensor_path(model: nn.Module) -> bool:
    """True when AdamW (foreach=None, fused=None) picks `_single_tensor_adam` for these parameters.

    Uses the same helper AdamW.step() calls; on CPU it returns (fused=False, foreach=False).
    """
    from torch.optim.optimizer import _default_to_fused_or_foreach

    fused, foreach = _default_to_fused_or_foreach(list(model.parameters()), differentiable=False, use_fused=False)
    return not fused and not foreach


def train_step(model, opt, sched, batch, prompt, grads_out: dict | None = None):
    """One reference gradient step. `batch` = (states, actions, rewards, returns_to_go, timesteps, mask).

    Returns (action_preds, loss, grad_norm, lr_used), detached. If `grads_out` is a dict, the
    pre-clipping gradients are copied into it (name -> tensor) for the parameters that got one.
    """
    states, actions, rewards, rtg, timesteps, mask = batch
    action_target = torch.clone(actions)
    _, action_preds, _ = model(states, actions, rewards, rtg, timesteps, mask, prompt=prompt)
    loss = masked_action_loss(action_preds, action_target, mask)
    opt.zero_grad()
    loss.backward()
    if grads_out is not None:
        for name, p in model.named_parameters():
            if p.grad is not None:
                grads_out[name] = p.grad.detach().clone()
    grad_norm = torch.nn.utils.clip_grad_norm_(model.parameters(), GRAD_CLIP)
    lr_used = opt.param_groups[0]["lr"]
    opt.step()
    sched.step()
    return action_preds.detach(), loss.detach(), grad_norm.detach(), lr_used


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def build_model(state_dim: int = 20, act_dim: int = 6) -> PromptDecisionTransformer:
    model = PromptDecisionTransformer(state_dim, act_dim)
    if (state_dim, act_dim) == (20, 6):
        n = count_parameters(model)
        assert n == 862_619, n
    assert len(model.state_dict()) == 67, len(model.state_dict())
    return model
