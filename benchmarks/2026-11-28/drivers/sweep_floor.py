#!/usr/bin/env python3
"""The arithmetic floor of the Figure 2 MuJoCo sweep at the paper budget (issue 30).

Counts the floating-point operations of one training step of the reference Prompt-DT model as
promptdt's pack computes it (every run at the pack's sequence length, the last block for the state
tokens only: `train.last_block = "auto"` on CUDA), for each MuJoCo family's batch, and the time the
sweep's 36 runs take at a given sustained rate. A lower bound on the device's time: it leaves out the
memory-bound work (LayerNorms, dropout, softmax, the optimiser), the evaluations and the host.

    python3 scripts/bench/sweep_floor.py --tflops 67 --tflops 50

Standard library only. The numbers in BENCHMARKS.md come from this command's output.
"""
import argparse

# Reference model (docs/implementation-details.md): width, depth, MLP width.
H, LAYERS, INNER = 128, 3, 4 * 128
K, PROMPT = 20, 5  # history steps; prompt steps (J x H = 1 x 5)
ITERATIONS, STEPS_PER_ITERATION = 5000, 10  # the paper budget
RUNS_PER_FAMILY = 12  # 4 methods x 3 seeds
# family: (train tasks, samples per task, state dim, action dim) (shared/reference, "Envs")
FAMILIES = {
    "cheetah_dir": (2, 16, 20, 6),
    "cheetah_vel": (35, 16, 20, 6),
    "ant_dir": (45, 16, 27, 8),
}


def forward_flops_per_sample(ds: int, da: int) -> float:
    steps = PROMPT + K
    l = 3 * steps  # tokens: (R, s, a) per step
    embed = steps * 2 * H * (ds + da + 1)  # the three input linears (timestep: a lookup)
    per_token_layer = 2 * H * 3 * H + 2 * H * H + 2 * H * INNER * 2  # c_attn, proj, MLP
    attention = 2 * 2 * l * H  # q.k over L keys and the weighted sum of L values, per query
    full = (LAYERS - 1) * l * (per_token_layer + attention)
    # The last block: keys and values of every token, the rest for the state tokens only.
    last = l * 2 * H * 2 * H + steps * (per_token_layer - 2 * H * 2 * H + attention)
    head = steps * 2 * H * da
    return embed + full + last + head


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tflops", type=float, action="append",
                    help="sustained float32 rate in TFLOP/s (repeatable); default 67, the H200's FP32 peak")
    args = ap.parse_args()
    rates = args.tflops or [67.0]
    steps = ITERATIONS * STEPS_PER_ITERATION
    print(f"{ITERATIONS} iterations x {STEPS_PER_ITERATION} steps, {RUNS_PER_FAMILY} runs per family, "
          f"forward + backward = 3 x forward\n")
    head = "| family | samples per step | GFLOP per run-step | PFLOP for 12 runs |"
    head += "".join(f" minutes at {r:g} TFLOP/s |" for r in rates)
    print(head)
    print("|---|---:|---:|---:|" + "---:|" * len(rates))
    total = 0.0
    for name, (tasks, per_task, ds, da) in FAMILIES.items():
        batch = tasks * per_task
        step = 3 * batch * forward_flops_per_sample(ds, da)
        sweep = step * steps * RUNS_PER_FAMILY
        total += sweep
        cells = "".join(f" {sweep / (r * 1e12) / 60:.1f} |" for r in rates)
        print(f"| {name} | {batch} | {step / 1e9:.1f} | {sweep / 1e15:.1f} |{cells}")
    cells = "".join(f" **{total / (r * 1e12) / 60:.1f}** |" for r in rates)
    print(f"| all 36 runs | | | {total / 1e15:.1f} |{cells}")


if __name__ == "__main__":
    main()
