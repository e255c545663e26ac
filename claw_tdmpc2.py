"""CLAW: Context-conditioned Low-rank Adaptation of World models, on TD-MPC2.

Pretrains a TD-MPC2 world model jointly with a hypernetwork that maps context transitions
(s, a, r, s') of one environment to LoRA adapters for the world model, over every environment
of a family (paper Alg. 1 and Alg. 2), then evaluates test-time adaptation: Exp 1 (online, one
hypernet pass before every planner call) and Exp 2 (offline, one pass then frozen).

Against DR (dr_tdmpc2.py: the same loop and data mix, no hypernetwork) CLAW adds what `diff dr_tdmpc2.py claw_tdmpc2.py`
shows: the hypernetwork (context -> LoRA adapters phi), a context pool of pi_con episodes per environment, the two-phase
update that trains the hypernetwork on the world-model and policy losses, and adapt: one hypernet pass, no gradient steps.

    python claw_tdmpc2.py --family reach --rank 16

Every step count (--total-timesteps, --seed-steps, --online-eval-steps, global_step) counts agent
steps, i.e. planner calls; with action repeat 2 that is half the simulator steps. Read top to bottom: Args,
math, networks, the method's own parts, planner, buffers, update, evaluation, main; the plumbing comes last.
"""

from __future__ import annotations

import copy
import math
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from collections import deque
from dataclasses import dataclass
from typing import Literal, Optional

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
import tyro
from torch.utils.tensorboard import SummaryWriter

from common.context import collect_episodes
from common.envs import FAMILIES, episode_length, is_metaworld, make_env, num_envs, render_problem, rng_state, set_rng_state
from common.evaluation import evaluate_family, global_rng_state, progress_bar, set_global_rng_state, weights_digest

# Paper Table "Per-family pretraining setup" (cheetah_walker: Exp 3-5, 250k per task).
DEFAULT_TOTAL_TIMESTEPS = {"walker": 600_000, "reach": 50_000, "push": 300_000, "go1": 1_000_000, "cheetah_walker": 500_000}
# Paper Table "Experiment 3 model-size sweep": encoder hidden, latent, MLP hidden, Q-ensemble size.
MODEL_SIZES = {
    "A": ([256], 512, 512, 5),
    "B": ([256], 128, 384, 2),
    "D": ([192], 48, 192, 2),
    "E": ([128], 32, 128, 2),
    "F": ([64], 32, 64, 2),
    "G": ([32], 32, 32, 2),
    "H": ([16], 32, 16, 2),
    "I": ([8], 32, 8, 2),
}


@dataclass
class Args:
    exp_name: str = os.path.basename(__file__)[: -len(".py")]
    """the name of this experiment"""
    family: Literal["walker", "reach", "push", "go1", "cheetah_walker"] = "reach"
    """environment family: walker, reach, push, go1, cheetah_walker"""
    seed: int = 1
    """seed of the experiment"""
    torch_deterministic: bool = True
    """if toggled, `torch.backends.cudnn.deterministic=True`"""
    cuda: bool = True
    """if toggled, cuda will be used when available"""
    threads: Optional[int] = None
    """torch CPU threads (default: torch's choice); use 1 per run when several runs share the cores"""
    compile: Literal["auto", "on", "off"] = "auto"
    """torch.compile the update and the planner (inductor; CUDA graphs for the planner on a GPU): same losses and updates
    as eager within float tolerance, faster steps after a one-off compile of ~2 min; auto: on for budgets of at least
    10,000 agent steps (on a 2-core CPU at size F it pays for itself after ~8,000; docs/speed.md)"""
    cudagraphs: bool = False
    """record the whole update (every phase, the optimiser steps included), the test-time gradient step and each kind of
    planner call as one CUDA graph each and replay them (tensordict's CudaGraphModule; with --compile or without): same
    results within float tolerance, less launch overhead; needs --cuda and a GPU"""
    total_timesteps: Optional[int] = None
    """pretraining agent steps (planner calls); default: the paper's per-family budget"""
    model_size: Optional[Literal["A", "B", "D", "E", "F", "G", "H", "I"]] = None
    """TD-MPC2 model size from the paper's size table (A = 5M parameters); default: A where CUDA is used, F on a CPU"""
    rank: int = 16
    """LoRA rank of the generated adapters"""
    dry_run: bool = False
    """build environments and networks, print the parameter counts and exit"""

    # CLAW hypernetwork (paper Table "arch"; the context pool and standardisation are our choice)

    adapter_l2: float = 0.01
    """lambda of the adapter L2 penalty"""
    hypernet_lr: float = 3e-4
    context_dim: int = 64
    embed_hidden: int = 256
    generator_hidden: int = 128
    chunk_size: int = 64
    chunk_embed_dim: int = 32
    context_pool_episodes: int = 20
    """pi_con episodes kept per environment; a pretraining context is --context-episodes of them"""
    context_refresh_every: int = 20
    """agent steps between pool refreshes, each replacing one environment's oldest episode (in turn); 0: never"""
    context_standardize: bool = True
    """standardise context features by per-feature statistics of the initial pool (kept in the checkpoint)"""
    decoder_coef: float = 0.0
    """weight of a reward decoder on u_con, a departure from the paper (0: none, the paper's method): an MLP predicts the
    update batch's symlog rewards from (s, a, s') and u_con, a direct identification signal for the context encoder"""

    # TD-MPC2 optimisation (paper Table "Optimization and planning hyperparameters")

    batch_size: int = 256
    learning_rate: float = 3e-4
    encoder_lr_scale: float = 0.3
    """encoder lr = learning_rate * encoder_lr_scale (9e-5)"""
    grad_clip_norm: float = 20.0
    horizon: int = 3
    rho: float = 0.5
    """temporal decay of the multi-step losses"""
    tau: float = 0.01
    """target critic EMA rate (decay 0.99)"""
    discount: float = 0.99
    """the paper's value for every family"""
    discount_heuristic: bool = False
    """use TD-MPC2's episode-length heuristic clip((L/5-1)/(L/5), 0.95, 0.995) instead of --discount (0.95 on Meta-World)"""
    consistency_coef: float = 20.0
    reward_coef: float = 0.1
    value_coef: float = 0.1
    entropy_coef: float = 1e-4
    num_bins: int = 101
    vmin: float = -10.0
    vmax: float = 10.0
    seed_steps: Optional[int] = None
    """random-action prefill; default max(1000, 5 x episode length)"""
    burst_updates: int = 1000
    """updates after the prefill, before rollouts begin"""

    # MPPI planner

    iterations: int = 6
    num_samples: int = 512
    num_pi_trajs: int = 24
    num_elites: int = 64
    temperature: float = 0.5
    min_std: float = 0.05
    max_std: float = 2.0

    # evaluation (paper Exp 1 / Exp 2)

    context_episodes: int = 3
    """pi_con episodes per context: each test environment's and (scripts with a hypernetwork) each pretraining draw"""
    online_eval_steps: int = 30_000
    """Exp 1 test-time agent steps per environment"""
    eval_episodes: int = 10
    """Exp 2 evaluation episodes per environment"""
    eval_env_ids: tuple[int, ...] = ()
    """the test environments both protocols run on (ids; default: every environment of the family)"""
    evaluate_after_training: bool = True
    """run both protocols on every environment after pretraining"""

    # logging and persistence

    log_every: int = 1000
    """agent steps between progress lines"""
    checkpoint_every: int = 50_000
    """checkpoint at the first episode end after every this many agent steps (and after the prefill and burst)"""
    checkpoint_minutes: float = 10.0
    """also checkpoint at the first episode end after this many minutes of wall-clock since the last one"""
    checkpoint: Optional[str] = None
    """checkpoint to evaluate with --eval-only"""
    eval_only: bool = False
    resume: Optional[str] = None
    """checkpoint of a killed run to continue with its saved arguments (only --threads, --cuda, --compile, --cudagraphs,
    --run-dir, --log-every, --checkpoint-every, --checkpoint-minutes, --track, --wandb-project-name, --wandb-entity,
    --capture-video may be given anew)"""
    run_dir: Optional[str] = None
    """default runs/{family}__{exp_name}__{seed}__{unix time}"""
    overwrite: bool = False
    """start over in a --run-dir that already holds a run (its checkpoint and TensorBoard events are deleted)"""
    track: bool = False
    """mirror the TensorBoard scalars and the hyperparameters to Weights & Biases (WANDB_MODE=offline: no network needed)"""
    wandb_project_name: str = "claw"
    """the Weights & Biases project"""
    wandb_entity: Optional[str] = None
    """the Weights & Biases entity (team); default: your default entity"""
    capture_video: bool = False
    """record the first Exp 2 (offline) episode of every test environment (of every --offline-adapt-steps setting, where there is
    a sweep) to {run_dir}/videos/env{id}_offline*.mp4; needs MUJOCO_GL=egl (GPU, or Mesa's software EGL) or MUJOCO_GL=osmesa (CPU)"""


# ---------------------------------------------------------------------------------------------
# Math: symlog two-hot regression (TD-MPC2)
# ---------------------------------------------------------------------------------------------
def symlog(x):
    return torch.sign(x) * torch.log1p(torch.abs(x))


def symexp(x):
    return torch.sign(x) * torch.expm1(torch.abs(x))


def two_hot(x, args: Args):
    """Scalars [..., 1] -> soft two-hot targets [..., num_bins] in symlog space."""
    bin_size = (args.vmax - args.vmin) / (args.num_bins - 1)
    x = (symlog(x).nan_to_num(nan=0.0).clamp(args.vmin, args.vmax) - args.vmin) / bin_size
    low = x.floor().clamp(max=args.num_bins - 2)
    upper_weight = x - low
    target = torch.zeros(*x.shape[:-1], args.num_bins, device=x.device)
    target.scatter_(-1, low.long(), 1 - upper_weight)
    return target.scatter_add_(-1, low.long() + 1, upper_weight)


def two_hot_inv(logits, args: Args):
    """Logits [..., num_bins] -> expected scalar [..., 1]."""
    bins = torch.linspace(args.vmin, args.vmax, args.num_bins, device=logits.device)
    return symexp(logits.softmax(-1) @ bins).unsqueeze(-1)


def soft_ce(logits, target, args: Args):
    """Cross-entropy of logits [..., num_bins] against scalar targets [..., 1] -> [..., 1]."""
    return -(two_hot(target, args) * logits.log_softmax(-1)).sum(-1, keepdim=True)


def mish(x):
    """Mish. Without autograd, the in-place form x * n / (n + 2), n = e^x (e^x + 2), is the same
    function at about half of F.mish's CPU cost, and the planner runs it ~100 times per call."""
    if torch.is_grad_enabled():
        return F.mish(x)
    e = x.clamp(max=20).exp_()
    n = e.mul_(e + 2)
    return n.div_(n + 2).mul_(x)


def simnorm(x, group_sums):
    """Softmax over groups of 8 features. exp / (exp @ block-diagonal ones) is ~10x cheaper on CPU
    than a softmax over a trailing dim of 8; inputs come out of a LayerNorm, so the clamp never
    bites in practice and only guards exp against overflow."""
    e = x.clamp(-60, 60).exp()
    return e / (e @ group_sums)


class RunningScale:
    """Running P95-P5 range of Q, used to normalise the policy objective (TD-MPC2)."""

    def __init__(self, tau: float, device):
        self.tau, self.value = tau, torch.ones((), device=device)
        self.points = torch.tensor([0.05, 0.95], device=device)  # on the device: no host copy inside an update

    def update(self, q):
        low, high = torch.quantile(q.detach().flatten().float(), self.points)
        self.value.lerp_(torch.clamp(high - low, min=1.0), self.tau)


# ---------------------------------------------------------------------------------------------
# Networks: the TD-MPC2 world model with every hidden layer's weight overridable
# ---------------------------------------------------------------------------------------------
class MLP(nn.Module):
    """Linear -> LayerNorm -> Mish layers, last layer plain Linear or Linear -> LayerNorm -> SimNorm.

    `ensemble > 0` stacks that many independent MLPs (the Q ensemble) as batched matmuls.
    `forward(x, weights)` takes the weight matrices from outside so LoRA-merged weights can be
    swapped in without touching the module; biases and LayerNorm stay the module's own."""

    def __init__(self, dims: list[int], simnorm_out: bool = False, ensemble: int = 0, dropout: float = 0.0):
        super().__init__()
        self.ensemble, self.dropout, self.simnorm_out = ensemble, dropout, simnorm_out
        self.num_normed = len(dims) - 1 if simnorm_out else len(dims) - 2
        lead = (ensemble,) if ensemble else ()
        self.weights = nn.ParameterList(
            nn.Parameter(nn.init.trunc_normal_(torch.empty(*lead, d_out, d_in), std=0.02))
            for d_in, d_out in zip(dims[:-1], dims[1:])
        )
        # ensemble biases/norm params carry a broadcast dim so they add onto [E, N, d_out]
        bias_shape = lambda d: (ensemble, 1, d) if ensemble else (d,)  # noqa: E731
        self.biases = nn.ParameterList(nn.Parameter(torch.zeros(bias_shape(d))) for d in dims[1:])
        self.norm_weights = nn.ParameterList(nn.Parameter(torch.ones(bias_shape(d))) for d in dims[1 : self.num_normed + 1])
        self.norm_biases = nn.ParameterList(nn.Parameter(torch.zeros(bias_shape(d))) for d in dims[1 : self.num_normed + 1])
        if simnorm_out:
            self.register_buffer("group_sums", torch.block_diag(*[torch.ones(8, 8)] * (dims[-1] // 8)), persistent=False)

    def forward(self, x, weights, detach: bool = False):
        """x: [N, d_in] ([E, N, d_in] or [N, d_in] for an ensemble) -> [N, d_out] ([E, N, d_out])."""
        for i, weight in enumerate(weights):
            bias = self.biases[i]
            if detach:  # a frozen copy: no gradient reaches this module (TD-MPC2's detached Q)
                weight, bias = weight.detach(), bias.detach()
            if self.ensemble:
                x = torch.baddbmm(bias, x.expand(self.ensemble, *x.shape[-2:]), weight.transpose(1, 2))
            else:
                x = F.linear(x, weight, bias)
            if i >= self.num_normed:
                continue
            if i == 0 and self.dropout > 0 and self.training:
                x = F.dropout(x, self.dropout)
            norm_w, norm_b = self.norm_weights[i], self.norm_biases[i]
            if detach:
                norm_w, norm_b = norm_w.detach(), norm_b.detach()
            if self.ensemble:
                x = torch.addcmul(norm_b, F.layer_norm(x, x.shape[-1:]), norm_w)
            else:
                x = F.layer_norm(x, x.shape[-1:], norm_w, norm_b)
            x = simnorm(x, self.group_sums) if i == len(weights) - 1 else mish(x)
        return x


class WorldModel(nn.Module):
    """TD-MPC2 state-based model: encoder, latent dynamics, reward, Q ensemble, policy prior."""

    # modules whose hidden layers get world-model adapters, then the policy's (separate slice)
    WORLD_MODEL_MODULES = ("encoder", "dynamics", "reward", "qs")

    def __init__(self, obs_dim: int, act_dim: int, model_size: str, args: Args):
        super().__init__()
        encoder_hidden, latent, hidden, num_q = MODEL_SIZES[model_size]
        self.obs_dim, self.act_dim, self.num_q, self.args = obs_dim, act_dim, num_q, args
        self.encoder = MLP([obs_dim, *encoder_hidden, latent], simnorm_out=True)
        self.dynamics = MLP([latent + act_dim, hidden, hidden, latent], simnorm_out=True)
        self.reward = MLP([latent + act_dim, hidden, hidden, args.num_bins])
        self.qs = MLP([latent + act_dim, hidden, hidden, args.num_bins], ensemble=num_q, dropout=0.01)
        self.policy = MLP([latent, hidden, hidden, 2 * act_dim])
        with torch.no_grad():  # zero-init the reward and value heads (TD-MPC2)
            self.reward.weights[-1].zero_()
            self.qs.weights[-1].zero_()
        self.target_qs = copy.deepcopy(self.qs).requires_grad_(False)

    def base_parameters(self):
        return [p for name, p in self.named_parameters() if not name.startswith("target_qs")]

    def base_weights(self) -> dict:
        """Weight matrices of every module, the input of the forward functions below."""
        names = (*self.WORLD_MODEL_MODULES, "policy", "target_qs")
        return {name: list(getattr(self, name).weights) for name in names}

    def encode(self, obs, weights):
        return self.encoder(obs, weights["encoder"])

    def next(self, z, action, weights):
        return self.dynamics(torch.cat([z, action], -1), weights["dynamics"])

    def reward_logits(self, z, action, weights):
        return self.reward(torch.cat([z, action], -1), weights["reward"])

    def pi(self, z, weights, detach: bool = False):
        """Squashed Gaussian policy prior: action, and its act_dim-scaled entropy."""
        mean, log_std = self.policy(z, weights["policy"], detach).chunk(2, -1)
        log_std = -10 + 6 * (torch.tanh(log_std) + 1)  # range [-10, 2]
        eps = torch.randn_like(mean)
        action = torch.tanh(mean + eps * log_std.exp())
        log_prob = (-0.5 * eps.pow(2) - log_std - 0.5 * math.log(2 * math.pi)).sum(-1, keepdim=True)
        log_prob = log_prob - torch.log(F.relu(1 - action.pow(2)) + 1e-6).sum(-1, keepdim=True)
        return action, -log_prob * self.act_dim

    def Q(self, z, action, weights, return_type: str, target: bool = False, detach: bool = False):
        """return_type 'all': logits [num_q, ..., bins]; 'min'/'avg' over two random heads: [..., 1]."""
        x = torch.cat([z, action], -1)
        lead = x.shape[:-1]
        mlp, key = (self.target_qs, "target_qs") if target else (self.qs, "qs")
        out = mlp(x.reshape(-1, x.shape[-1]), weights[key], detach)
        out = out.view(self.num_q, *lead, -1)
        if return_type == "all":
            return out
        heads = torch.randperm(self.num_q, device=out.device)[:2]
        q1, q2 = two_hot_inv(out[heads], self.args).unbind(0)
        return torch.min(q1, q2) if return_type == "min" else (q1 + q2) / 2


# ---------------------------------------------------------------------------------------------
# LoRA: W = W0 + A B on every hidden (LayerNorm'd) Linear; one flat parameter vector phi
# ---------------------------------------------------------------------------------------------
def lora_layout(model: WorldModel, rank: int) -> tuple[list[tuple], int, int]:
    """[(module, layer, A shape, B shape, offset)], n_wm, n_pi: phi[:n_wm] adapts the world model, phi[n_wm:] the policy."""
    layout, offset, sizes = [], 0, []
    for group in (model.WORLD_MODEL_MODULES, ("policy",)):
        start = offset
        for name in group:
            mlp = getattr(model, name)
            for layer in range(mlp.num_normed):
                *lead, d_out, d_in = mlp.weights[layer].shape
                a_shape, b_shape = (*lead, d_out, rank), (*lead, rank, d_in)
                layout.append((name, layer, a_shape, b_shape, offset))
                offset += math.prod(a_shape) + math.prod(b_shape)
        sizes.append(offset - start)
    return layout, sizes[0], sizes[1]


def lora_template(layout, num_params: int) -> torch.Tensor:
    """Initial phi: A = 0 and B random, a zero update that still passes gradient to A (and to whatever generates it)."""
    phi = torch.zeros(num_params)
    for _, _, a_shape, b_shape, offset in layout:
        start = offset + math.prod(a_shape)
        nn.init.trunc_normal_(phi[start : start + math.prod(b_shape)], std=0.02)
    return phi


def adapted_weights(model: WorldModel, phi, layout) -> dict:
    """Merge adapters phi into the base weights; the target critic gets the same adapter, detached, never EMA'd."""
    weights = model.base_weights()
    for name, layer, a_shape, b_shape, offset in layout:
        mid = offset + math.prod(a_shape)
        delta = phi[offset:mid].view(a_shape) @ phi[mid : mid + math.prod(b_shape)].view(b_shape)
        weights[name][layer] = weights[name][layer] + delta
        if name == "qs":
            weights["target_qs"][layer] = weights["target_qs"][layer] + delta.detach()
    return weights


# ---------------------------------------------------------------------------------------------
# Hypernetwork: context transitions -> LoRA adapters phi (paper Fig. "hypernet-forward")
# ---------------------------------------------------------------------------------------------
def hidden_mlp(d_in: int, d_hidden: int, d_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(d_in, d_hidden), nn.LayerNorm(d_hidden), nn.Mish(), nn.Linear(d_hidden, d_out))


class ContextEncoder(nn.Module):
    """Standardise, h_emb per transition, mean pool (order-free), h_con -> context embedding u_con."""

    def __init__(self, transition_dim: int, args: Args):
        super().__init__()
        self.register_buffer("feature_mean", torch.zeros(transition_dim))  # identity until set_statistics
        self.register_buffer("feature_std", torch.ones(transition_dim))
        self.embed = nn.Sequential(hidden_mlp(transition_dim, args.embed_hidden, args.embed_hidden), nn.Mish())
        self.context = hidden_mlp(args.embed_hidden, args.embed_hidden, args.context_dim)
        # --decoder-coef: r from (s, a, s') and u_con; only u_con tells the environments' rewards apart
        self.reward_decoder = (
            hidden_mlp(transition_dim + args.context_dim, args.embed_hidden, 1) if args.decoder_coef > 0 else None
        )

    def set_statistics(self, transitions):
        """Fix the per-feature standardisation; constant features (std ~0) are only centred."""
        std = transitions.std(0)
        self.feature_mean.copy_(transitions.mean(0))
        self.feature_std.copy_(torch.where(std > 1e-6, std, torch.ones_like(std)))

    def forward(self, transitions):  # [N, transition_dim] -> [context_dim]
        return self.context(self.embed((transitions - self.feature_mean) / self.feature_std).mean(0))

    def decoder_loss(self, u_con, obs, action, reward):
        """MSE of the decoded symlog(r) of replay transitions [H, B] of u_con's environment (--decoder-coef), their rows
        (s, a, r, s') laid out and standardised as context rows."""
        rows = (torch.cat([obs[:-1], action, torch.zeros_like(reward), obs[1:]], -1) - self.feature_mean) / self.feature_std
        rows[..., obs.shape[-1] + action.shape[-1]] = 0.0  # the reward is what the decoder predicts
        return F.mse_loss(self.reward_decoder(torch.cat([rows, u_con.expand(*rows.shape[:-1], -1)], -1)), symlog(reward))


class Hypernet(nn.Module):
    """phi = phi_0 + concat_k h_gen([u_con, u_k]) cut to N_adapt, generated in chunks of 64."""

    def __init__(self, transition_dim: int, template: torch.Tensor, args: Args):
        super().__init__()
        self.num_params = template.numel()
        num_chunks = math.ceil(self.num_params / args.chunk_size)
        self.encoder = ContextEncoder(transition_dim, args)
        self.chunk_embeddings = nn.Parameter(torch.randn(num_chunks, args.chunk_embed_dim))
        d_in, hidden = args.context_dim + args.chunk_embed_dim, args.generator_hidden
        self.generator = nn.Sequential(
            hidden_mlp(d_in, hidden, hidden), nn.LayerNorm(hidden), nn.Mish(), nn.Linear(hidden, args.chunk_size)
        )
        nn.init.zeros_(self.generator[-1].weight)  # delta phi = 0 at init: adapters start as the template
        nn.init.zeros_(self.generator[-1].bias)
        self.template = nn.Parameter(template.clone())

    def forward(self, transitions):
        return self.generate(self.encoder(transitions))

    def generate(self, u_con):
        chunk_input = torch.cat([u_con.expand(len(self.chunk_embeddings), -1), self.chunk_embeddings], -1)
        return self.template + self.generator(chunk_input).flatten()[: self.num_params]


# ---------------------------------------------------------------------------------------------
# MPPI planner: TD-MPC2's, batched over all samples
# ---------------------------------------------------------------------------------------------
@torch.no_grad()
def estimate_value(model: WorldModel, weights, z, actions, discount: float, args: Args):
    """Discounted predicted rewards over the horizon plus the bootstrapped Q: [num_samples, 1]."""
    value, gamma = 0.0, 1.0
    for t in range(args.horizon):
        value = value + gamma * two_hot_inv(model.reward_logits(z, actions[t], weights), args)
        z = model.next(z, actions[t], weights)
        gamma *= discount
    return value + gamma * model.Q(z, model.pi(z, weights)[0], weights, "avg")


@torch.no_grad()
def plan(model: WorldModel, weights, obs, prev_mean, discount: float, args: Args, explore: bool):
    """One MPPI planner call -> (action [act_dim], mean [horizon, act_dim] to warm-start the next)."""
    device, horizon, act_dim = obs.device, args.horizon, model.act_dim
    z = model.encode(obs.unsqueeze(0), weights)
    actions = torch.empty(horizon, args.num_samples, act_dim, device=device)
    z_pi = z.expand(args.num_pi_trajs, -1)
    for t in range(horizon):  # policy-seeded trajectories
        actions[t, : args.num_pi_trajs] = model.pi(z_pi, weights)[0]
        if t < horizon - 1:
            z_pi = model.next(z_pi, actions[t, : args.num_pi_trajs], weights)
    z = z.expand(args.num_samples, -1)
    mean = torch.zeros(horizon, act_dim, device=device)
    if prev_mean is not None:
        mean[:-1] = prev_mean[1:]
    std = torch.full((horizon, act_dim), args.max_std, device=device)
    num_random = args.num_samples - args.num_pi_trajs
    for _ in range(args.iterations):
        noise = torch.randn(horizon, num_random, act_dim, device=device)
        actions[:, args.num_pi_trajs :] = (mean.unsqueeze(1) + std.unsqueeze(1) * noise).clamp(-1, 1)
        value = estimate_value(model, weights, z, actions, discount, args).nan_to_num(0).squeeze(1)
        elite_value, elite_idxs = torch.topk(value, args.num_elites)
        elite_actions = actions[:, elite_idxs]
        score = torch.softmax(args.temperature * elite_value, 0)
        mean = (score.view(1, -1, 1) * elite_actions).sum(1)
        std = (
            (score.view(1, -1, 1) * (elite_actions - mean.unsqueeze(1)).pow(2)).sum(1).sqrt().clamp(args.min_std, args.max_std)
        )
    action = elite_actions[0, torch.multinomial(score, 1)[0]]
    if explore:
        action = action + std[0] * torch.randn(act_dim, device=device)
    return action.clamp(-1, 1), mean


# ---------------------------------------------------------------------------------------------
# Buffers: replay of planner episodes and context of pi_con episodes, one slice per environment
# ---------------------------------------------------------------------------------------------
class ReplayBuffer:
    """Flat transition storage for all environments; samples (horizon+1)-step windows that stay
    inside one episode of one environment (episodes are stored contiguously)."""

    def __init__(self, capacity: int, obs_dim: int, act_dim: int, n_envs: int, horizon: int, device):
        self.horizon, self.device, self.size, self.episode_start = horizon, device, 0, 0
        self.obs = torch.empty(capacity, obs_dim, device=device)
        self.next_obs = torch.empty(capacity, obs_dim, device=device)
        self.action = torch.empty(capacity, act_dim, device=device)
        self.reward = torch.empty(capacity, 1, device=device)
        self.starts = [torch.empty(0, dtype=torch.long) for _ in range(n_envs)]  # valid window starts per env
        self.pending = [[] for _ in range(n_envs)]

    def add(self, env_id: int, obs, action, reward: float, next_obs, first: bool):
        if self.size == len(self.obs):
            raise RuntimeError("replay buffer full: capacity is total_timesteps plus the prefill")
        pos = self.size
        self.obs[pos] = torch.as_tensor(obs, device=self.device)
        self.next_obs[pos] = torch.as_tensor(next_obs, device=self.device)
        self.action[pos] = torch.as_tensor(action, device=self.device)
        self.reward[pos] = reward
        self.size += 1
        if first:
            self.episode_start = pos
        if pos - self.episode_start >= self.horizon - 1:
            self.pending[env_id].append(pos - self.horizon + 1)

    def num_starts(self, env_id: int) -> int:
        return len(self.starts[env_id]) + len(self.pending[env_id])

    def sample(self, env_id: int, batch_size: int):
        """-> obs [H+1, B, obs_dim], action [H, B, act_dim], reward [H, B, 1]."""
        if self.pending[env_id]:
            self.starts[env_id] = torch.cat([self.starts[env_id], torch.tensor(self.pending[env_id])])
            self.pending[env_id] = []
        starts = self.starts[env_id]
        idx = starts[torch.randint(len(starts), (batch_size,))].to(self.device)
        steps = idx.unsqueeze(0) + torch.arange(self.horizon, device=self.device).unsqueeze(1)  # [H, B]
        obs = torch.cat([self.obs[idx].unsqueeze(0), self.next_obs[steps]], 0)
        return obs, self.action[steps], self.reward[steps]

    def state_dict(self) -> dict:
        for env_id in range(len(self.starts)):
            if self.pending[env_id]:
                self.starts[env_id] = torch.cat([self.starts[env_id], torch.tensor(self.pending[env_id])])
                self.pending[env_id] = []
        n = self.size  # copies: torch.save writes a view's whole storage, here the buffer's full capacity
        return {
            "obs": self.obs[:n].to("cpu", copy=True),
            "next_obs": self.next_obs[:n].to("cpu", copy=True),
            "action": self.action[:n].to("cpu", copy=True),
            "reward": self.reward[:n].to("cpu", copy=True),
            "starts": self.starts,
            "size": n,
        }

    def load_state_dict(self, state: dict):
        n = self.size = state["size"]
        for key in ("obs", "next_obs", "action", "reward"):
            getattr(self, key)[:n] = state[key].to(self.device)
        self.starts = state["starts"]
        self.episode_start = n  # the interrupted episode is dropped; the next one starts fresh


def context_tensor(context: dict, device) -> torch.Tensor:
    """pi_con transitions as hypernet input rows (s, a, r, s')."""
    parts = (context["obs"], context["action"], context["reward"][:, None], context["next_obs"])
    return torch.as_tensor(np.concatenate(parts, 1), dtype=torch.float32, device=device)


class ContextPool:
    """Pretraining contexts: whole pi_con episodes per environment, drawn as at test time (--context-episodes
    of them); refreshed during training so that no fixed set of episodes can identify an environment."""

    def __init__(self, envs: list, args: Args, device):
        self.envs, self.args, self.device, self.episodes, self.collected = envs, args, device, [[] for _ in envs], 0

    def fill(self, encoder: nn.Module):  # paper Alg. 1, lines 1-2; the initial pool fixes the standardisation
        for _ in progress_bar(range(self.args.context_pool_episodes), desc="context pool"):
            for env_id in range(len(self.envs)):
                self.collect(env_id)
        if self.args.context_standardize:
            encoder.set_statistics(torch.cat(sum(self.episodes, [])))

    def collect(self, env_id: int):
        # a new episode every time, never an evaluation seed (those lie below --seed + 50,000)
        seed = (1_000_000 * self.args.seed if self.args.seed > 0 else 10**9) + self.collected
        self.episodes[env_id].append(context_tensor(collect_episodes(self.envs[env_id], 1, seed=seed), self.device))
        self.collected += 1

    def refresh(self, global_step: int):  # every --context-refresh-every steps, one environment in turn
        every = self.args.context_refresh_every
        if every and global_step % every == 0 and self.episodes[0]:  # an unfilled pool stays empty
            env_id = global_step // every % len(self.envs)
            self.episodes[env_id].pop(0)
            self.collect(env_id)

    def sample(self, env_id: int) -> torch.Tensor:
        pool = self.episodes[env_id]
        return torch.cat([pool[i] for i in torch.randperm(len(pool))[: self.args.context_episodes].tolist()])


# ---------------------------------------------------------------------------------------------
# Update (paper Alg. 2 TDMPC2Update): phase 1 world model + hypernet, phase 2 policy + hypernet
# ---------------------------------------------------------------------------------------------
def world_model_loss(model: WorldModel, weights, obs, action, reward, discount: float, args: Args):
    """TD-MPC2 world-model loss -> (loss, latents [H+1, B, latent], info)."""
    with torch.no_grad():
        next_z = model.encode(obs[1:], weights)
        td_target = reward + discount * model.Q(next_z, model.pi(next_z, weights)[0], weights, "min", target=True)
    z = model.encode(obs[0], weights)
    zs, consistency = [z], 0.0
    for t in range(args.horizon):
        z = model.next(z, action[t], weights)
        consistency = consistency + args.rho**t * F.mse_loss(z, next_z[t])
        zs.append(z)
    zs = torch.stack(zs)
    rho = args.rho ** torch.arange(args.horizon, device=obs.device, dtype=torch.float32)
    reward_ce = soft_ce(model.reward_logits(zs[:-1], action, weights), reward, args).mean((1, 2))
    q_logits = model.Q(zs[:-1], action, weights, "all")  # [num_q, H, B, bins]
    value_ce = soft_ce(q_logits, td_target.unsqueeze(0).expand(model.num_q, -1, -1, -1), args).mean((2, 3)).sum(0)
    consistency = consistency / args.horizon
    reward_loss = (reward_ce * rho).mean()
    value_loss = (value_ce * rho).mean() / model.num_q
    loss = args.consistency_coef * consistency + args.reward_coef * reward_loss + args.value_coef * value_loss
    return (
        loss,
        zs,
        {"consistency_loss": consistency.detach(), "reward_loss": reward_loss.detach(), "value_loss": value_loss.detach()},
    )


def policy_loss(model: WorldModel, weights, zs, scale: RunningScale, args: Args):
    """Maximise scaled Q plus entropy on detached latents; Q's weights are detached."""
    action, scaled_entropy = model.pi(zs, weights)
    q = model.Q(zs, action, weights, "avg", detach=True)
    scale.update(q[0])
    rho = args.rho ** torch.arange(len(q), device=q.device, dtype=torch.float32)
    return (-(args.entropy_coef * scaled_entropy + q / scale.value).mean((1, 2)) * rho).mean()


def update(model, hypernet, optimizers, scale, layout, n_wm, obs, action, reward, context, discount, args: Args) -> dict:
    wm_optimizer, pi_optimizer, hyper_optimizer = optimizers
    model.train()
    # phase 1: world-model base slice and hypernet on the world-model loss + adapter penalty (+ reward decoder)
    u_con = hypernet.encoder(context)
    phi = hypernet.generate(u_con)
    weights = adapted_weights(model, phi, layout)
    wm_loss, zs, info = world_model_loss(model, weights, obs, action, reward, discount, args)
    adapter_penalty = args.adapter_l2 * phi[:n_wm].pow(2).sum()
    decoder_loss = hypernet.encoder.decoder_loss(u_con, obs, action, reward) if args.decoder_coef > 0 else 0.0
    if args.decoder_coef > 0:
        info["decoder_loss"] = decoder_loss.detach()
    wm_optimizer.zero_grad(set_to_none=True)
    hyper_optimizer.zero_grad(set_to_none=True)
    (wm_loss + adapter_penalty + args.decoder_coef * decoder_loss).backward()
    wm_params = [p for g in wm_optimizer.param_groups for p in g["params"]]
    grad_norm = nn.utils.clip_grad_norm_(wm_params + list(hypernet.parameters()), args.grad_clip_norm)
    wm_optimizer.step()
    hyper_optimizer.step()
    # phase 2: regenerate the policy adapter with the updated hypernet; policy slice and hypernet
    phi_pi = hypernet(context)[n_wm:]
    weights = adapted_weights(model, torch.cat([phi[:n_wm].detach(), phi_pi]), layout)
    pi_loss = policy_loss(model, weights, zs.detach(), scale, args) + args.adapter_l2 * phi_pi.pow(2).sum()
    pi_optimizer.zero_grad(set_to_none=True)
    hyper_optimizer.zero_grad(set_to_none=True)
    pi_loss.backward()
    nn.utils.clip_grad_norm_(list(model.policy.parameters()) + list(hypernet.parameters()), args.grad_clip_norm)
    pi_optimizer.step()
    hyper_optimizer.step()
    # target critic: EMA of the base weights only
    with torch.no_grad():
        torch._foreach_lerp_(list(model.target_qs.parameters()), list(model.qs.parameters()), args.tau)
    model.eval()
    info.update(wm_loss=wm_loss.detach(), pi_loss=pi_loss.detach(), grad_norm=grad_norm, adapter_norm=phi.detach().norm())
    return info


def make_optimizers(model: WorldModel, hypernet: nn.Module, args: Args):
    wm_optimizer = torch.optim.Adam(
        [
            {"params": model.encoder.parameters(), "lr": args.learning_rate * args.encoder_lr_scale},
            {"params": [*model.dynamics.parameters(), *model.reward.parameters(), *model.qs.parameters()]},
        ],
        lr=args.learning_rate,
    )
    pi_optimizer = torch.optim.Adam(model.policy.parameters(), lr=args.learning_rate, eps=1e-5)
    hyper_optimizer = torch.optim.Adam(hypernet.parameters(), lr=args.hypernet_lr)
    return wm_optimizer, pi_optimizer, hyper_optimizer


# ---------------------------------------------------------------------------------------------
# Evaluation: the shared protocols with CLAW's adapt (one hypernet pass) and act (MPPI)
# ---------------------------------------------------------------------------------------------
def evaluation_env_ids(args: Args) -> list[int]:
    """The test environments evaluate() runs: --eval-env-ids, or every environment of the family."""
    return list(args.eval_env_ids) or list(range(num_envs(args.family)))


def evaluate(model, hypernet, layout, discount, writer, device, args: Args, progress_path: str | None = None) -> dict:
    model.eval()
    current = {"weights": model.base_weights(), "mean": None}

    @torch.no_grad()
    def adapt(context):
        current["weights"] = adapted_weights(model, hypernet(context_tensor(context, device)), layout)

    def act(obs, first_step):
        obs = torch.as_tensor(obs, dtype=torch.float32, device=device)
        action, current["mean"] = plan(
            model, current["weights"], obs, None if first_step else current["mean"], discount, args, explore=False
        )
        return action.cpu().numpy()

    return evaluate_family(
        evaluation_env_ids(args),
        adapt,
        act,
        writer,
        args,
        progress_path=progress_path,
        after_each_env=lambda: stop_if_interrupted(progress_path and os.path.dirname(progress_path)),
        weights=weights_digest(model, hypernet),
    )


# ---------------------------------------------------------------------------------------------
# Main: set-up, context collection, prefill, burst, online pretraining loop, evaluation
# ---------------------------------------------------------------------------------------------
def main(args: Args, typed: set | None = None):
    started = time.time()
    validate_args(args)
    purge_step = None
    if args.resume or args.eval_only:  # the checkpoint's arguments; a flag given explicitly with another value is an error
        saved = read_checkpoint(args.resume or args.checkpoint)
        # flags that shape the saved weights: the shared ones, then the method's own
        architecture = ("family", "model_size", "num_bins", "vmin", "vmax", "horizon", "discount", "discount_heuristic")
        architecture += ("context_dim", "embed_hidden", "decoder_coef")
        architecture += ("generator_hidden", "chunk_size", "chunk_embed_dim", "rank")
        # --eval-only: the run's own evaluation unless given anew
        free = RESUME_FREE + (() if args.resume else EVALUATION_FLAGS)
        adopt_args(
            args,
            saved["args"],
            None if args.resume else architecture + EVALUATION_FLAGS,
            args.resume or args.checkpoint,
            typed,
            free,
        )
        # checkpoints are large: keep only the step
        purge_step, saved = saved["global_step"] + 1 if args.resume else None, None
    if args.model_size is None:  # one line before any work: the paper's size A on a GPU, F on a CPU
        args.model_size = default_model_size(args)
        where = "CUDA" if args.model_size == "A" else "a CPU"
        print(f"model size {args.model_size}: the default on {where} (--model-size A is the paper's size)", flush=True)
    total_timesteps, seed_steps, prefill = validate_args(args)
    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    torch.backends.cudnn.deterministic = args.torch_deterministic
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    device = torch.device("cuda" if torch.cuda.is_available() and args.cuda else "cpu")
    if args.compile == "auto":  # measured break-even: docs/speed.md
        args.compile = "on" if total_timesteps >= 10_000 else "off"
    accelerate(device, args)  # --compile, --cudagraphs: every call below, evaluation included, takes the fast functions

    n_envs, ep_len = num_envs(args.family), episode_length(args.family)
    envs = [make_env(args.family, env_id, seed=args.seed + env_id) for env_id in range(n_envs)]
    for env_id, env in enumerate(envs):
        env.action_space.seed(args.seed + env_id)
    obs_dim, act_dim = envs[0].observation_space.shape[0], envs[0].action_space.shape[0]
    discount = default_discount(args, ep_len)

    model = WorldModel(obs_dim, act_dim, args.model_size, args).to(device)
    layout, n_wm, n_pi = lora_layout(model, args.rank)
    hypernet = Hypernet(2 * obs_dim + act_dim + 1, lora_template(layout, n_wm + n_pi), args).to(device)
    print(f"base parameters: {sum(p.numel() for p in model.base_parameters())}")
    print(f"adapter parameters: {n_wm} (world model) + {n_pi} (policy)", flush=True)
    print(f"hypernetwork parameters: {sum(p.numel() for p in hypernet.parameters())}", flush=True)
    if args.dry_run:
        return
    print(describe_device(args, device))
    # one line at the start, not a traceback at the first video
    if args.capture_video and (problem := render_problem(args.family)):
        print(f"warning: --capture-video records nothing: {problem}", flush=True)
        args.capture_video = False
    if not args.eval_only:  # what the run will do, before it does it
        burst = f"{args.burst_updates} burst updates"
        print(f"budget: {total_timesteps} agent steps: a {prefill}-step random prefill, {burst}, then training", flush=True)
        print(describe_evaluation(args) if args.evaluate_after_training else "evaluation: none", flush=True)

    if args.resume and args.run_dir is None:  # keep logging into the interrupted run
        args.run_dir = os.path.dirname(os.path.abspath(args.resume))
    run_dir = args.run_dir or f"runs/{args.family}__{args.exp_name}__{args.seed}__{int(time.time())}"
    check_run_dir(run_dir, args)
    if args.track:  # before the SummaryWriter, whose scalars W&B mirrors (sync_tensorboard)
        import wandb

        wandb.init(
            project=args.wandb_project_name,
            entity=args.wandb_entity,
            sync_tensorboard=True,
            config=vars(args),
            name=os.path.basename(os.path.abspath(run_dir)),
            save_code=True,
        )
    writer = SummaryWriter(run_dir, purge_step=purge_step)  # a resumed run replaces the events logged after its checkpoint
    writer.add_text(
        "hyperparameters",
        hyperparameter_text(args, total_timesteps=total_timesteps, seed_steps=seed_steps, discount=discount, device=device),
    )
    scale = RunningScale(args.tau, device)
    if args.eval_only:
        print(describe_evaluation(args), flush=True)
        load_checkpoint(args.checkpoint, model, hypernet)
        evaluate(model, hypernet, layout, discount, writer, device, args)
        writer.close()
        if args.track:
            wandb.finish()
        return

    optimizers = make_optimizers(model, hypernet, args)
    capturable(optimizers, args.cudagraphs)  # --cudagraphs: Adam's step counts on the device
    replay = ReplayBuffer(total_timesteps + seed_steps + n_envs * ep_len, obs_dim, act_dim, n_envs, args.horizon, device)
    checkpoint_path = os.path.join(run_dir, "checkpoint.pt")
    global_step, burst_left, saved_at, saved_step = 0, args.burst_updates, time.time(), 0
    clock = RunClock(args, total_timesteps, len(evaluation_env_ids(args)), ep_len)  # the estimate of how long the run takes

    def save():  # atomic; also right after the prefill and the burst, and every --checkpoint-minutes
        nonlocal saved_at, saved_step
        save_checkpoint(checkpoint_path, global_step, burst_left, model, hypernet, optimizers, scale, replay, pool, args, envs)
        saved_at, saved_step = time.time(), global_step
        stop_if_interrupted(run_dir, global_step)

    context_envs = [make_env(args.family, env_id, seed=args.seed + 200 + env_id) for env_id in range(n_envs)]
    pool = ContextPool(context_envs, args, device)
    if args.resume:
        state = load_checkpoint(args.resume, model, hypernet, optimizers, scale, replay, restore_rng=True)
        capturable(optimizers, args.cudagraphs)  # the loaded state brings the setting of the run that wrote it
        pool.episodes, pool.collected = [[e.to(device) for e in p] for p in state["contexts"][0]], state["contexts"][1]
        global_step, burst_left, saved_step = state["global_step"], state.get("burst_left", 0), state["global_step"]
        for env, env_rng in zip(envs, state["rng"].get("envs", [])):  # checkpoints are written at episode ends
            set_rng_state(env, env_rng)
        print(f"resumed from {args.resume} at step {global_step}", flush=True)
    else:
        pool.fill(hypernet.encoder)  # pi_con episodes per environment
        global_step += random_prefill(dict(enumerate(envs)), replay, prefill)  # update buffers: every environment
        save()
    if burst_left:  # also a run killed during its burst: it resumes from the checkpoint after the prefill
        print(f"prefilled {global_step} steps; {burst_left} burst updates", flush=True)
        for _ in progress_bar(range(burst_left), desc="burst"):
            k = random.randrange(n_envs)
            batch = replay.sample(k, args.batch_size)
            info = update(model, hypernet, optimizers, scale, layout, n_wm, *batch, pool.sample(k), discount, args)
            stop_if_diverged(info, global_step, checkpoint_path)
            clock.lap("update")
        burst_left = 0
        save()

    first, prev_mean = True, None  # an episode starts at the top of the loop, also where a resumed run continues
    # recent: (return, success) of the last episodes
    start_time, start_step, recent = time.time(), global_step, deque(maxlen=10)
    while global_step < total_timesteps:
        if first:  # a new episode in a rollout environment drawn per episode
            rollout_env = random.randrange(n_envs)
            obs, _ = envs[rollout_env].reset()
            rollout_context = pool.sample(rollout_env)  # one context per episode, as at test time
            episode_return = 0.0
        # ALGO LOGIC: the method's update, then plan and act
        # update the base and hypernet on a training environment sampled per step
        k = random.randrange(n_envs)
        batch = replay.sample(k, args.batch_size)
        info = update(model, hypernet, optimizers, scale, layout, n_wm, *batch, pool.sample(k), discount, args)
        stop_if_diverged(info, global_step, checkpoint_path)
        # plan and act in the rollout environment, weights freshly computed from its context
        with torch.no_grad():
            weights = adapted_weights(model, hypernet(rollout_context), layout)
        action, prev_mean = plan(
            model,
            weights,
            torch.as_tensor(obs, dtype=torch.float32, device=device),
            None if first else prev_mean,
            discount,
            args,
            explore=True,
        )
        action = action.cpu().numpy()
        # TRY NOT TO MODIFY: step the environment, record the transition, log and checkpoint
        next_obs, reward, terminated, truncated, step_info = envs[rollout_env].step(action)
        replay.add(rollout_env, obs, action, reward, next_obs, first)
        episode_return += float(reward)
        obs, first, global_step = next_obs, False, global_step + 1
        if terminated or truncated:
            writer.add_scalar("charts/episodic_return", episode_return, global_step)
            writer.add_scalar("charts/episodic_success", float(step_info.get("success", 0.0)), global_step)
            writer.add_scalar(f"charts/env{envs[rollout_env].unwrapped.env_id}/episodic_return", episode_return, global_step)
            recent.append((episode_return, float(step_info.get("success", 0.0))))
            first = True
        pool.refresh(global_step)
        clock.lap("step", global_step)
        if global_step % args.log_every == 0 or global_step == total_timesteps:
            sps = int((global_step - start_step) / (time.time() - start_time))
            for key, value in info.items():
                writer.add_scalar(f"losses/{key}", value.item(), global_step)
            writer.add_scalar("charts/q_scale", float(scale.value), global_step)
            writer.add_scalar("charts/SPS", sps, global_step)
            print(
                f"step {global_step}/{total_timesteps} | wm_loss {float(info['wm_loss']):.3f} | "
                f"adapter_norm {float(info['adapter_norm']):.3f} | {progress_text(global_step, total_timesteps, start_step, start_time, started, recent, args.family)}",
                flush=True,
            )
            writer.flush()
        if first and (
            global_step // args.checkpoint_every > saved_step // args.checkpoint_every
            or time.time() - saved_at > 60 * args.checkpoint_minutes
            or STOP_SIGNAL
        ):
            save()  # deferred to an episode's end: a resumed run then starts the next episode as this run does
    save()
    print(f"saved {checkpoint_path}", flush=True)
    if args.evaluate_after_training:
        progress_path = os.path.join(run_dir, "evaluation_progress.pt")  # resumes an interrupted evaluation
        evaluate(model, hypernet, layout, discount, writer, device, args, progress_path=progress_path)
    writer.close()
    if args.track:
        wandb.finish()


# ---------------------------------------------------------------------------------------------
# Argument checks: every flag against its range, before any work
# ---------------------------------------------------------------------------------------------
def validate_args(args: Args) -> tuple[int, int, int]:
    if args.family not in FAMILIES:
        raise SystemExit(f"error: unknown family {args.family!r}; valid families: {', '.join(FAMILIES)}")
    if not 0 < args.num_elites <= args.num_samples or not 0 <= args.num_pi_trajs < args.num_samples:
        raise SystemExit(
            "error: need 0 < --num-elites <= --num-samples and 0 <= --num-pi-trajs < --num-samples, got "
            f"{args.num_elites}, {args.num_samples}, {args.num_pi_trajs}"
        )
    for name in ("checkpoint", "resume"):
        path = getattr(args, name)
        if path is not None and not os.path.isfile(path):
            raise SystemExit(f"error: --{name} {path!r} does not exist")
    if not 1 <= args.context_episodes <= args.context_pool_episodes or args.context_refresh_every < 0:
        pool = f"--context-episodes ({args.context_episodes}) <= --context-pool-episodes ({args.context_pool_episodes})"
        raise SystemExit(f"error: need 1 <= {pool} and --context-refresh-every >= 0")
    if args.eval_only and args.checkpoint is None:
        raise SystemExit("error: --eval-only needs --checkpoint PATH")
    if args.checkpoint is not None and not args.eval_only:
        raise SystemExit("error: --checkpoint is read by --eval-only only; to continue training a run use --resume PATH")
    if args.eval_only and args.resume:
        raise SystemExit("error: --eval-only and --resume exclude each other")
    check_counts(
        args,
        (
            "total_timesteps",
            "batch_size",
            "horizon",
            "iterations",
            "num_samples",
            "log_every",
            "checkpoint_every",
            "checkpoint_minutes",
            "threads",
            "rank",
            "context_episodes",
            "eval_episodes",
            "context_dim",
            "embed_hidden",
            "generator_hidden",
            "chunk_size",
            "chunk_embed_dim",
        ),
        ("online_eval_steps", "burst_updates", "seed_steps", "decoder_coef"),
    )
    if args.num_bins < 2 or args.vmin >= args.vmax:
        raise SystemExit(f"error: need --num-bins >= 2 and --vmin < --vmax, got {args.num_bins}, {args.vmin}, {args.vmax}")
    check_ranges(args)
    budget = resolve_budget(args)  # (total agent steps, --seed-steps, prefill agent steps)
    if not (args.eval_only or args.dry_run):  # the budget matters only to a training run
        check_budget(budget[0], budget[2])
    return budget


def default_discount(args: Args, episode_length: int) -> float:
    """--discount (the paper's 0.99), or with --discount-heuristic TD-MPC2's clip((L/5-1)/(L/5), 0.95, 0.995)."""
    if not args.discount_heuristic:
        return args.discount
    return min(max((episode_length / 5 - 1) / (episode_length / 5), 0.95), 0.995)


# ---------------------------------------------------------------------------------------------
# Run plumbing: checked checkpoints, the resume contract, compile rebinding, progress
# ---------------------------------------------------------------------------------------------
# flags that cannot change a run's results: --resume takes them anew if given, else from the checkpoint
RESUME_FREE = (
    "threads",
    "cuda",
    "compile",
    "cudagraphs",
    "log_every",
    "checkpoint_every",
    "checkpoint_minutes",
    "track",
    "wandb_project_name",
    "wandb_entity",
    "capture_video",
)
NOT_SAVED = ("run_dir", "resume", "checkpoint", "eval_only", "dry_run", "overwrite")  # this invocation's own


def flag(key: str) -> str:
    return "--" + key.replace("_", "-")


# numeric flags' valid ranges, checked before any work (flags a script lacks are skipped): flag -> (test, range in words)
MAX_SEED = 2**32 - 1 - 100_000  # NumPy takes seeds up to 2**32 - 1, and the environments' seeds add up to 50,000 + env id
RANGES = {
    "seed": (lambda v: 0 <= v <= MAX_SEED, f"an integer in 0..{MAX_SEED}"),
    "learning_rate": (lambda v: v > 0, "> 0"),
    "hypernet_lr": (lambda v: v > 0, "> 0"),
    "encoder_lr_scale": (lambda v: v > 0, "> 0"),
    "grad_clip_norm": (lambda v: v > 0, "> 0"),
    "rho": (lambda v: 0 < v <= 1, "in (0, 1]"),
    "tau": (lambda v: 0 < v <= 1, "in (0, 1]"),
    "discount": (lambda v: 0 < v <= 1, "in (0, 1]"),
    "temperature": (lambda v: v > 0, "> 0"),
    "min_std": (lambda v: v > 0, "> 0"),
    "consistency_coef": (lambda v: v >= 0, ">= 0"),
    "reward_coef": (lambda v: v >= 0, ">= 0"),
    "value_coef": (lambda v: v >= 0, ">= 0"),
    "entropy_coef": (lambda v: v >= 0, ">= 0"),
    "adapter_l2": (lambda v: v >= 0, ">= 0"),
    "decoder_coef": (lambda v: v >= 0, ">= 0"),
}
# flags an --eval-only run takes from the checkpoint unless given anew: how the run was evaluated and planned
EVALUATION_FLAGS = (
    "context_episodes",
    "online_eval_steps",
    "offline_adapt_steps",
    "eval_episodes",
    "eval_env_ids",
    "iterations",
    "num_samples",
    "num_pi_trajs",
    "num_elites",
    "temperature",
    "min_std",
    "max_std",
)


def check_ranges(args: Args):
    """One error line for the first flag out of its range (RANGES, the std and two-hot ranges, the horizon against the
    episode, the rank against the model's narrowest adapted layer) or not finite."""
    for key, value in vars(args).items():
        if isinstance(value, float) and not math.isfinite(value):
            raise SystemExit(f"error: {flag(key)} must be finite, got {value}")
    for key, (valid, text) in RANGES.items():
        if hasattr(args, key) and not valid(getattr(args, key)):
            raise SystemExit(f"error: {flag(key)} must be {text}, got {getattr(args, key)}")
    ids, n_envs = getattr(args, "eval_env_ids", ()), num_envs(args.family)  # posthoc evaluates cheetah only
    if len(set(ids)) < len(ids) or not all(0 <= e < n_envs for e in ids):
        raise SystemExit(f"error: --eval-env-ids must be distinct ids in 0..{n_envs - 1} ({args.family}), got {list(ids)}")
    if args.min_std > args.max_std:
        raise SystemExit(f"error: need --min-std <= --max-std, got {args.min_std} > {args.max_std}")
    if not 0 < args.horizon < episode_length(args.family):
        raise SystemExit(
            f"error: --horizon must be in 1..{episode_length(args.family) - 1} (below {args.family}'s episode "
            f"length), got {args.horizon}"
        )
    if args.cudagraphs and not (args.cuda and torch.cuda.is_available()):
        where = "CUDA is not available here" if args.cuda else "--no-cuda was given"
        raise SystemExit(f"error: --cudagraphs needs --cuda and a GPU ({where}); leave it out or give --no-cudagraphs")
    size = args.model_size or default_model_size(args)
    encoder_hidden, _, mlp_hidden, _ = MODEL_SIZES[size]
    narrowest = min([*encoder_hidden, mlp_hidden])
    if hasattr(args, "rank") and not 1 <= args.rank <= narrowest:
        raise SystemExit(
            f"error: --rank must be in 1..{narrowest} (the narrowest adapted layer of model size {size}), got {args.rank}"
        )


def typed_flags(argv: list[str]) -> set[str]:
    """The Args fields named on a command line (--flag, --flag=value, --no-flag): given explicitly, even with the default value."""
    fields = set(Args.__dataclass_fields__)
    names = {word[2:].split("=", 1)[0].replace("-", "_") for word in argv if word.startswith("--")}
    return {name if name in fields else name.removeprefix("no_") for name in names} & fields


def describe_evaluation(args: Args) -> str:
    """What an evaluation will run, in one line, with the flags that shorten it."""
    sweep = f", the Exp 2 sweep {list(args.offline_adapt_steps)} adapter steps" if hasattr(args, "offline_adapt_steps") else ""
    return (
        f"evaluation per test environment: Exp 1 {args.online_eval_steps} online agent steps, Exp 2 {args.eval_episodes} "
        f"episodes{sweep}; planner {args.num_samples} samples x {args.iterations} iterations "
        "(shorter: --online-eval-steps, --eval-episodes)"
    )


def check_run_dir(run_dir: str, args: Args):
    """A --run-dir that already holds a run (a checkpoint or TensorBoard events) is not reused without a word: its
    checkpoint would be overwritten and two runs' events mixed. --overwrite deletes them and starts over."""
    if args.resume or not os.path.isdir(run_dir):
        return
    held = sorted(
        n
        for n in os.listdir(run_dir)
        if n in ("checkpoint.pt", "evaluation_progress.pt") or n.startswith("events.out.tfevents")
    )
    if held and not args.overwrite:
        resume = f"continue it with --resume {os.path.join(run_dir, 'checkpoint.pt')}, " if "checkpoint.pt" in held else ""
        raise SystemExit(f"error: --run-dir {run_dir} already holds a run ({held[0]}); {resume}or start over with --overwrite")
    for name in held:
        os.remove(os.path.join(run_dir, name))


STOP_SIGNAL = []  # the signal (SIGINT, SIGTERM) that asked this run to stop at its next exact resume point


def stop_gracefully_on_signals():
    """SIGINT/SIGTERM: the run goes on to the next point where resume is exact (an episode's end, the end of the prefill
    or burst, an evaluated environment), saves, prints how to resume and exits 128 + the signal; a second one stops at once."""

    def handler(signum, frame):
        if STOP_SIGNAL:
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)
        STOP_SIGNAL.append(signum)
        print(
            f"{signal.Signals(signum).name}: saving at the next episode end, then stopping (again: stop at once)", flush=True
        )

    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, handler)


def stop_if_interrupted(run_dir: str | None, step: int | None = None):
    """After a save: exit if a signal asked the run to stop, with the command that resumes it."""
    if not STOP_SIGNAL:
        return
    name = signal.Signals(STOP_SIGNAL[0]).name
    if run_dir is None:
        print(f"{name}: stopped; an --eval-only run keeps no progress, run it again", flush=True)
    else:
        at = f" at step {step}" if step is not None else " during the evaluation (its progress is saved)"
        resume = f"python {os.path.basename(__file__)} --resume {os.path.join(run_dir, 'checkpoint.pt')}"
        print(f"{name}: stopped{at}; resume with: {resume}", flush=True)
    raise SystemExit(128 + STOP_SIGNAL[0])


def stop_if_diverged(info: dict, step: int, checkpoint_path: str | None):
    """A non-finite loss or gradient norm ends the run with one line: the step, the quantity, the last finite checkpoint."""
    watched = {k: v for k, v in info.items() if "loss" in k or k == "grad_norm"}  # not e.g. posthoc's NaN adapter_norm
    values = torch.stack([torch.as_tensor(v, dtype=torch.float32).detach().reshape(()).cpu() for v in watched.values()])
    if bool(torch.isfinite(values).all()):
        return
    key, value = next((k, v) for k, v in zip(watched, values) if not torch.isfinite(v))
    kept = f"; {checkpoint_path} holds the last finite weights" if checkpoint_path and os.path.exists(checkpoint_path) else ""
    raise SystemExit(
        f"error: the run diverged at step {step}: {key} is {float(value)}{kept}; lower --learning-rate or --grad-clip-norm"
    )


def atomic_save(state: dict, path: str):
    """torch.save to path.tmp, then rename: a kill mid-save never leaves a truncated file. A failed write (a full disk)
    ends the run with one line, the temporary file removed and the previous file intact; so do non-finite weights (a
    diverged run), so that the file on disk keeps the last finite ones."""
    if any(not bool(torch.isfinite(t).all()) for t in state.get("model", {}).values() if t.is_floating_point()):
        raise SystemExit(
            f"error: the run diverged before step {state.get('global_step')}: its weights are not finite; "
            f"{path} keeps the last finite ones; lower --learning-rate or --grad-clip-norm"
        )
    try:
        torch.save(state, path + ".tmp")
    except (OSError, RuntimeError) as error:  # a full disk: OSError, or RuntimeError ("unexpected pos") from the zip writer
        if os.path.exists(path + ".tmp"):
            os.remove(path + ".tmp")
        detail = str(error).splitlines()[0] if str(error) else type(error).__name__
        kept = "; the previous one is intact" if os.path.exists(path) else ""
        raise SystemExit(
            f"error: cannot write {path} ({detail}; {shutil.disk_usage(os.path.dirname(os.path.abspath(path))).free // 2**20} MiB "
            f"free){kept}"
        ) from None
    os.replace(path + ".tmp", path)


def check_counts(args: Args, positive: tuple[str, ...], nonnegative: tuple[str, ...] = ()):
    """One error line for the first count out of range, before any work; keys this script lacks are skipped."""
    for key in positive:
        value = getattr(args, key, None)
        if value is not None and value <= 0:
            raise SystemExit(
                f"error: {flag(key)} must be a positive {'number' if isinstance(value, float) else 'integer'}, got {value}"
            )
    for key in nonnegative:
        value = getattr(args, key, None)
        if value is not None and value < 0:
            raise SystemExit(f"error: {flag(key)} must be >= 0, got {value}")


def resolve_budget(args: Args, n_envs: int | None = None, envs_filled: int | None = None) -> tuple[int, int, int]:
    """(total agent steps, --seed-steps, prefill agent steps) with the paper's defaults filled in. The prefill is
    whole random-action episodes: --seed-steps spread over n_envs environments (default the family's), at least
    one episode each, of which envs_filled (default all) are actually rolled."""
    ep_len = episode_length(args.family)
    n_envs = num_envs(args.family) if n_envs is None else n_envs
    total = args.total_timesteps if args.total_timesteps is not None else DEFAULT_TOTAL_TIMESTEPS[args.family]
    seed_steps = args.seed_steps if args.seed_steps is not None else max(1000, 5 * ep_len)
    prefill = max(1, math.ceil(seed_steps / (n_envs * ep_len))) * (n_envs if envs_filled is None else envs_filled) * ep_len
    return total, seed_steps, prefill


def check_budget(budget: int, prefill: int, what: str = "--total-timesteps"):
    if budget <= prefill:
        raise SystemExit(
            f"error: {what}: {budget} must exceed the random-action prefill of {prefill} steps "
            "(whole episodes, at least one per environment); raise it or lower --seed-steps"
        )


def read_checkpoint(path: str, model=None) -> dict:
    """torch.load with one error line for an unreadable file, another script's checkpoint, or (given
    the model it is loaded into) another family, model size or observation/action dimension."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as error:  # truncated, corrupt or not a torch file: torch raises many types
        detail = f"{type(error).__name__}: {str(error).splitlines()[0]}" if str(error) else type(error).__name__
        raise SystemExit(f"error: cannot read checkpoint {path} (truncated, corrupt or not a torch file): {detail}") from None
    if not isinstance(state, dict) or not isinstance(state.get("args"), dict) or "model" not in state:
        raise SystemExit(f"error: {path} is not a checkpoint of these scripts (no saved 'args' and 'model')")
    found = state.get("method", f"{state['args'].get('exp_name')}.py")  # older checkpoints: the run's exp_name
    if found != os.path.basename(__file__):
        raise SystemExit(f"error: {path} is a {found} checkpoint, expected one written by {os.path.basename(__file__)}")
    if model is not None:
        expected = {"family": model.args.family, "model_size": model.args.model_size, "dims": (model.obs_dim, model.act_dim)}
        found = {**state["args"], "dims": tuple(state.get("dims", expected["dims"]))}
        for key, value in expected.items():
            if found.get(key, value) != value:
                raise SystemExit(f"error: {path} holds {key} {found[key]}, expected {value}")
    return state


def mismatch(error: Exception) -> str:
    """The first informative line of a load_state_dict error (which lists every tensor)."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    return next(
        (line for line in lines if "size mismatch" in line or "Missing" in line or "Unexpected" in line),
        lines[0] if lines else "",
    )


def adopt_args(args: Args, saved: dict, keys, path: str, typed: set | None = None, free=RESUME_FREE):
    """Set args.key = saved[key] for keys (None: every saved argument). A flag given explicitly (named on the command
    line, typed; or, where typed is None, differing from the Args default) with another value than the saved one is an
    error, except the free ones (RESUME_FREE by default), which keep the given value."""
    defaults = Args()
    for key in [k for k in saved if k not in NOT_SAVED] if keys is None else keys:
        if key not in saved or not hasattr(args, key):
            continue
        given = getattr(args, key)
        explicit = key in typed if typed is not None else given != getattr(defaults, key)
        if explicit and given != saved[key]:
            if key in free:
                continue
            raise SystemExit(
                f"error: {flag(key)} {given} conflicts with {saved[key]} in {path}; leave it out to use the checkpoint's"
            )
        setattr(args, key, saved[key])


def accelerate(device: torch.device, args: Args):
    """--compile and --cudagraphs: rebinds the module's hot functions, the update, the planner and (where the script has
    one) the test-time gradient step, so that every later call takes the fast ones. With --cudagraphs each is recorded
    whole by graphed(), on top of the compiled function when --compile is on (then compiled without inductor's own CUDA
    graphs)."""
    hot = globals()
    for name in ("update", "plan", "adapt_step"):
        if name not in hot:
            continue
        if args.compile == "on":
            hot[name] = compiled(hot[name], device, cuda_graphs=name == "plan" and not args.cudagraphs)
        if args.cudagraphs:
            hot[name] = graphed(hot[name])


def compiled(fn, device: torch.device, cuda_graphs: bool = True):
    """--compile: torch.compile(fn), its compile time printed at the first call. On a GPU with cuda_graphs, CUDA graphs
    ("reduce-overhead"), the outputs cloned because the next replay overwrites them (not for the updates: their graph
    breaks at backward() split them into graphs whose outputs the next piece overwrites; --cudagraphs records them
    whole instead, graphed()). Inductor's pattern matcher is off: it crashes on this code (torch 2.11 CUDA, 2.13 CPU:
    "Not all inputs to pattern found in match.kwargs")."""
    if getattr(fn, "is_compiled", False):  # main() run twice in one process
        return fn
    graphs = device.type == "cuda" and cuda_graphs
    import torch._inductor.config as inductor_config

    inductor_config.pattern_matcher = False
    compiled_fn, first_call = torch.compile(fn, mode="reduce-overhead" if graphs else None), [True]

    def call(*args, **kwargs):
        if graphs:
            torch.compiler.cudagraph_mark_step_begin()
        start = time.time()
        out = compiled_fn(*args, **kwargs)
        if first_call[0]:
            first_call[0] = False
            print(
                f"compiled {fn.__name__} in {time.time() - start:.0f} s (first call; new input kinds compile again)",
                flush=True,
            )
        return torch.utils._pytree.tree_map_only(torch.Tensor, torch.clone, out) if graphs else out

    call.is_compiled = True
    return call


def graphed(fn, warmup: int = 3):
    """--cudagraphs: fn recorded whole as one CUDA graph per kind of call and replayed (tensordict's CudaGraphModule).
    A kind of call is what a replay cannot take anew, bound to its graph when recorded: the arguments that are not
    tensors (model, optimisers, Args, the planner's explore flag, a missing warm-start mean) and the tensors that require
    gradients (parameters, test-time adapters), which the graph reads and updates in place; and the shapes of the other
    tensors (batch, context, merged weights, observation), which each call copies into the graph's input buffers. The
    first warmup - 1 calls of a kind run fn as it is (compiling it under --compile), the next one records it; outputs
    come back as clones, since the next replay overwrites the graph's own."""
    if getattr(fn, "is_graphed", False):  # main() run twice in one process
        return fn
    from tensordict.nn import CudaGraphModule

    flatten, unflatten = torch.utils._pytree.tree_flatten, torch.utils._pytree.tree_unflatten
    graphs = {}  # kind -> the CudaGraphModule, whose function holds the bound arguments (so their ids stay theirs)

    def call(*args):
        leaves, spec = flatten(args)
        copied = [isinstance(x, torch.Tensor) and not x.requires_grad for x in leaves]
        kind = (spec, *(x.shape if c else x if isinstance(x, (int, float, str)) else id(x) for x, c in zip(leaves, copied)))
        if kind not in graphs:
            bound = [None if c else x for x, c in zip(leaves, copied)]

            def with_bound(*tensors, bound=bound, copied=copied, spec=spec):
                given = iter(tensors)
                return fn(*unflatten([next(given) if c else x for x, c in zip(bound, copied)], spec))

            graphs[kind] = CudaGraphModule(with_bound, warmup=warmup)
        return graphs[kind](*(x for x, c in zip(leaves, copied) if c))

    call.graphs, call.is_graphed, call.is_compiled = graphs, True, getattr(fn, "is_compiled", False)
    return call


def capturable(optimizers, on: bool):
    """--cudagraphs: Adam with capturable=True, its step counts on the parameters' device, so that a recorded optimiser
    step reads no host value; off: the default, step counts on the host. Set before the first update and after a
    checkpoint's optimiser state is loaded, which brings the setting of the run that wrote it."""
    for optimizer in optimizers:
        for group in optimizer.param_groups:
            group["capturable"] = on
        for param, state in optimizer.state.items():
            if "step" in state:
                state["step"] = state["step"].to(param.device if on else "cpu")


def describe_device(args: Args, device: torch.device) -> str:
    """Start-up lines: the device, a warning when CUDA was asked for but is missing, a size hint."""
    lines = [f"device: {device}"]
    if args.cuda and device.type == "cpu":
        lines.append(
            "warning: --cuda was asked for but CUDA is not available; running on the CPU (slow; --no-cuda silences this)"
        )
    if device.type == "cpu" and args.model_size in ("A", "B"):
        lines.append(f"hint: model size {args.model_size} is slow on a CPU; --model-size F trains in a fraction of the time")
    return "\n".join(lines)


def default_model_size(args: Args) -> str:
    """Without --model-size: the paper's size A where CUDA is used, F on a CPU (A costs ~74 GFLOP per agent step)."""
    return "A" if args.cuda and torch.cuda.is_available() else "F"


class RunClock:
    """Times the burst's updates and the first training steps (medians, so a first call's compile does not count) and
    prints once, after the first 30 training steps, how long the rest of training and the evaluation will take here."""

    def __init__(self, args: Args, total_timesteps: int, n_test_envs: int, episode_length: int):
        self.args, self.total, self.n_test_envs, self.episode_length = args, total_timesteps, n_test_envs, episode_length
        self.seconds, self.last, self.printed = {"update": [], "step": []}, None, False

    def lap(self, kind: str, step: int | None = None):
        """After a burst update (kind "update") or a training step ("step", with global_step)."""
        now = time.perf_counter()
        if self.last is not None and self.last[0] == kind:
            self.seconds[kind].append(now - self.last[1])
        self.last = (kind, now)
        if kind == "step" and not self.printed and len(self.seconds["step"]) >= 30:
            self.printed = True
            print(self.estimate(step), flush=True)

    def estimate(self, step: int) -> str:
        args, step_s = self.args, float(np.median(self.seconds["step"]))
        update_s = float(np.median(self.seconds["update"])) if self.seconds["update"] else step_s / 2
        sweep = getattr(args, "offline_adapt_steps", (0,))  # gradient methods' Exp 2 sweep; one pass otherwise
        exp1 = args.online_eval_steps * step_s  # an online step adapts, plans and acts
        exp2 = len(sweep) * args.eval_episodes * self.episode_length * max(step_s - update_s, 0) + sum(sweep) * update_s
        evaluation = self.n_test_envs * (exp1 + exp2) if args.evaluate_after_training else 0.0
        return (
            f"estimate on this machine: training {hms((self.total - step) * step_s)} more ({1000 * step_s:.0f} ms per "
            f"agent step), evaluation {hms(evaluation)} ({self.n_test_envs} test environments, Exp 1 {hms(exp1)} and "
            f"Exp 2 {hms(exp2)} each; shorter: --online-eval-steps, --eval-episodes)"
        )


def git_commit() -> str:
    try:
        root = os.path.dirname(os.path.abspath(__file__))
        return subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, check=True
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def hyperparameter_text(args: Args, **resolved) -> str:
    """The TensorBoard hyperparameter table with resolved values (no None for a default)."""
    values = {**vars(args), **resolved, "git_commit": git_commit()}
    return "|param|value|\n|-|-|\n" + "\n".join(f"|{k}|{v}|" for k, v in values.items())


def hms(seconds: float) -> str:
    seconds = int(max(0, seconds))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


def progress_text(step: int, total: int, start_step: int, start_time: float, started: float, recent, family: str) -> str:
    """'return R | success S | SPS n | elapsed h:mm:ss | ETA h:mm:ss': mean of the recent (return, success)
    episodes, agent steps per second since start_time (at start_step), elapsed since started."""
    now = time.time()
    rate = (step - start_step) / max(now - start_time, 1e-9)
    parts = [f"return {sum(r for r, _ in recent) / len(recent):.1f}" if recent else "return -"]
    if is_metaworld(family):
        parts.append(f"success {sum(s for _, s in recent) / len(recent):.2f}" if recent else "success -")
    eta = hms((total - step) / rate) if rate > 0 else "-"
    return " | ".join(parts + [f"SPS {int(rate)}", f"elapsed {hms(now - started)}", f"ETA {eta}"])


def random_prefill(envs: dict, replay, total: int) -> int:
    """Random-action prefill of `total` agent steps, split evenly over the environments ({replay slice:
    env}) in whole episodes, with a progress bar; returns the agent steps taken."""
    steps, bar = 0, progress_bar(total=total, desc="prefill")
    for env_id, env in envs.items():
        env_steps = 0
        while env_steps < total // len(envs):
            obs, _ = env.reset()
            done, first = False, True
            while not done:
                action = env.action_space.sample()
                next_obs, reward, terminated, truncated, _ = env.step(action)
                replay.add(env_id, obs, action, reward, next_obs, first)
                obs, first, done, env_steps = next_obs, False, terminated or truncated, env_steps + 1
                bar.update()
        steps += env_steps
    bar.close()
    return steps


# ---------------------------------------------------------------------------------------------
# Persistence
# ---------------------------------------------------------------------------------------------
def save_checkpoint(path, global_step, burst_left, model, hypernet, optimizers, scale, replay, pool, args: Args, envs=()):
    state = {
        "global_step": global_step,
        "burst_left": burst_left,
        "args": vars(args),
        "model": model.state_dict(),
        "hypernet": hypernet.state_dict(),
        "optimizers": [opt.state_dict() for opt in optimizers],
        "scale": scale.value.cpu(),
        "replay": replay.state_dict() if replay is not None else None,
        "contexts": (pool.episodes, pool.collected),
        "method": os.path.basename(__file__),
        "dims": (model.obs_dim, model.act_dim),  # checked by read_checkpoint
        "rng": {**global_rng_state(), "envs": [rng_state(env) for env in envs]},  # envs: the rollout environments' next resets
    }
    atomic_save(state, path)


def load_checkpoint(path, model, hypernet, optimizers=None, scale=None, replay=None, restore_rng: bool = False):
    state = read_checkpoint(path, model)
    try:  # one line, not a size-mismatch traceback per tensor
        model.load_state_dict(state["model"])
        hypernet.load_state_dict(state["hypernet"])
    except (KeyError, RuntimeError) as error:
        raise SystemExit(f"error: {path} does not fit this configuration: {mismatch(error)}") from None
    if optimizers is not None:
        for opt, opt_state in zip(optimizers, state["optimizers"]):
            opt.load_state_dict(opt_state)
    if scale is not None:
        scale.value.copy_(state["scale"])
    if replay is not None and state["replay"] is not None:
        replay.load_state_dict(state["replay"])
    if restore_rng:
        set_global_rng_state(state["rng"])
    return state


if __name__ == "__main__":
    stop_gracefully_on_signals()
    main(tyro.cli(Args), typed=typed_flags(sys.argv[1:]))
