//! Command-line arguments (what the user typed). Each becomes a validated library config.

use crate::prompt_args::{bandit_rule, prompt_strategy, AdaptFlags, ServeAdaptFlags};
use crate::results_args::ResultsCommand;
use anyhow::Result;
use clap::{Args, Parser, Subcommand};
use pdt_base::device::DeviceSpec;
use std::path::PathBuf;

#[derive(Debug, Parser)]
#[command(
    name = "promptdt",
    version,
    about = "Prompt-based Decision Transformer (Xu et al., ICML 2022) in Rust"
)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
    /// Stop when standard input reaches its end: `reproduce` gives its `collect` and `train`
    /// children a pipe it holds, so they stop when it dies, however it dies.
    #[arg(long, global = true, hide = true)]
    pub die_with_parent: bool,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// Inspect and convert offline datasets.
    #[command(subcommand)]
    Data(DataCommand),
    /// Run a model on stored inputs.
    #[command(subcommand)]
    Model(ModelCommand),
    /// RL agents that make the datasets (see `collect`).
    #[command(subcommand)]
    Agent(AgentCommand),
    /// Collect offline datasets (expert / medium / random) and prompt sets.
    Collect(CollectArgs),
    /// Train Prompt-DT or a variant from a TOML configuration.
    Train(TrainArgs),
    /// Few-shot evaluation of a run's latest checkpoint on its held-out tasks.
    Eval(EvalArgs),
    /// Tables and learning-curve plots from run directories.
    Report(ReportArgs),
    /// Environment tools.
    #[command(subcommand)]
    Env(EnvCommand),
    /// Time training steps and inference against PyTorch (`bench render`: BENCHMARKS.md from
    /// the records in `benchmarks/`).
    #[command(args_conflicts_with_subcommands = true)]
    Bench(crate::bench_args::BenchArgs),
    /// A quick end-to-end run.
    Demo(DemoArgs),
    /// Reproduce a table or figure of the paper: run what is not finished, then report it next to
    /// the paper's numbers (`--list` shows the experiments).
    Reproduce(ReproduceArgs),
    /// Serve a trained run's prompted policy over HTTP+JSON (docs/serve.md).
    Serve(ServeArgs),
    /// A prompted policy's episode as an animated GIF, its return in the corner
    /// (docs/rendering.md).
    Render(RenderArgs),
    /// The results registry (`results/`): archive finished runs, generate RESULTS.md.
    #[command(subcommand)]
    Results(ResultsCommand),
}

#[derive(Debug, Args)]
pub struct ServeArgs {
    /// Run directory (its latest checkpoint is served).
    #[arg(long)]
    pub run: PathBuf,
    /// Address to listen on (port 0: any free port; the address is printed).
    #[arg(long, default_value = "127.0.0.1:8000")]
    pub listen: std::net::SocketAddr,
    #[arg(long)]
    pub device: Option<DeviceSpec>,
    /// Where the run's data moved (for `task` prompts).
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Episodes open at once.
    #[arg(long, default_value_t = 1024, value_parser = count(1, 1_000_000))]
    pub max_episodes: usize,
    /// Requests answered by one forward at most.
    #[arg(long, default_value_t = 256, value_parser = count(1, 65_536))]
    pub max_batch: usize,
    /// How long to wait for more requests before a forward, in milliseconds (0: none).
    #[arg(long, default_value_t = 2, value_parser = count(0, 10_000))]
    pub batch_wait_ms: usize,
    /// Close an episode after this many seconds without a request (up to a week).
    #[arg(long, default_value_t = 300, value_parser = count(1, 604_800))]
    pub idle_timeout_s: usize,
    /// Largest request body in bytes.
    #[arg(long, default_value_t = 1 << 20, value_parser = count(64, 1 << 30))]
    pub max_body_bytes: usize,
    /// Close a connection that has not sent a request's headers within this many seconds (also
    /// an idle kept-alive connection).
    #[arg(long, default_value_t = 10, value_parser = count(1, 3600))]
    pub header_timeout_s: usize,
    /// Give up a request whose body has not arrived this many seconds after its headers (408).
    #[arg(long, default_value_t = 10, value_parser = count(1, 3600))]
    pub body_timeout_s: usize,
    /// Connections open at once; one more is answered 503 and closed. Default: 512, or fewer
    /// when the descriptor limit (ulimit -n) leaves less room (it minus 64).
    #[arg(long, value_parser = count(1, 1_000_000))]
    pub max_connections: Option<usize>,
    /// libtorch threads of the model thread. With 1 (the default) an episode's actions are
    /// bit-identical to `promptdt eval`'s and do not depend on the other episodes of its batch.
    #[arg(long, default_value_t = 1, value_parser = count(1, 1024))]
    pub threads: usize,
    /// Prompt strategy of episodes opened with a `task` (docs/prompt-control.md; a request's
    /// `prompt_strategy` overrides it): reference (default), random-segment, best-return,
    /// nearest-start, bandit (one per task, learning from the returns of closed episodes).
    #[arg(long, value_parser = prompt_strategy)]
    pub prompt_strategy: Option<pdt_prompt::PromptStrategyKind>,
    /// Test-time prompt segments J of `task` prompts (default: the run's).
    #[arg(long, value_parser = count(1, 1000))]
    pub prompt_episodes: Option<usize>,
    /// Test-time steps per prompt segment H of `task` prompts (default: the run's).
    #[arg(long, value_parser = count(1, 100_000))]
    pub prompt_length: Option<usize>,
    #[command(flatten)]
    pub adaptation: ServeAdaptFlags,
    /// Require `Authorization: Bearer <token>` with the token in this file (whitespace around it
    /// ignored; at least 16 characters) on every request but GET /v1/health. Without it the
    /// token is read from PROMPTDT_SERVE_TOKEN when set. A token is needed on an address other
    /// than loopback (docs/serve.md, Authentication).
    #[arg(long, conflicts_with_all = ["generate_token", "no_auth"])]
    pub token_file: Option<PathBuf>,
    /// Require a bearer token made now at random, printed once (`token: ...`, the line after the
    /// address) and kept nowhere.
    #[arg(long, conflicts_with = "no_auth")]
    pub generate_token: bool,
    /// Serve without authentication on an address other than loopback (anyone who reaches the
    /// port can use the server; for a server behind a proxy that authenticates). Prints a
    /// warning.
    #[arg(long)]
    pub no_auth: bool,
}

impl ServeArgs {
    /// Who may use the server, from `--token-file`, `--generate-token`, `--no-auth` and
    /// PROMPTDT_SERVE_TOKEN (a flag wins over the variable; `--no-auth` with the variable set is
    /// a contradiction, refused); and a generated token's text, to be printed once.
    pub fn auth(&self) -> anyhow::Result<(pdt_serve::Auth, Option<String>)> {
        use pdt_serve::{auth::TOKEN_ENV, Auth, Token};
        if let Some(path) = &self.token_file {
            return Ok((Auth::Token(Token::from_file(path)?), None));
        }
        if self.generate_token {
            let (token, text) = Token::generate()?;
            return Ok((Auth::Token(token), Some(text)));
        }
        let from_env = Token::from_env(TOKEN_ENV)?;
        Ok(match (from_env, self.no_auth) {
            (Some(_), true) => anyhow::bail!(
                "--no-auth, but the environment variable {TOKEN_ENV} holds a token: unset it to \
                 serve without authentication, or drop --no-auth to require it"
            ),
            (Some(t), false) => (Auth::Token(t), None),
            (None, true) => (Auth::Disabled, None),
            (None, false) => (Auth::LoopbackOnly, None),
        })
    }
}

#[derive(Debug, Args)]
pub struct RenderArgs {
    /// Run directory (its latest checkpoint acts).
    #[arg(long)]
    pub run: PathBuf,
    /// Task index of the run's family; the prompt is drawn from the run's data of that task.
    #[arg(long)]
    pub task: usize,
    /// The animated GIF to write (`.gif`).
    #[arg(long)]
    pub out: PathBuf,
    /// Frame width in pixels (at most 640).
    #[arg(long, default_value_t = 160)]
    pub width: usize,
    /// Frame height in pixels (at most 480).
    #[arg(long, default_value_t = 120)]
    pub height: usize,
    /// Frames a second (1 to 100).
    #[arg(long, default_value_t = 20)]
    pub fps: u32,
    /// Stop after this many steps (default: the whole episode).
    #[arg(long)]
    pub max_steps: Option<usize>,
    /// Seeds the reset and the prompt's draw.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    #[arg(long)]
    pub device: Option<DeviceSpec>,
    /// Where the run's data moved (prompts are drawn from it).
    #[arg(long)]
    pub data: Option<PathBuf>,
}

#[derive(Debug, Args)]
pub struct ReproduceArgs {
    /// Experiment name (fig2, table1, fig3, fig4, appendix_*) or a manifest file.
    #[arg(required_unless_present = "list")]
    pub experiment: Option<String>,
    /// List every experiment with its cost per budget.
    #[arg(long)]
    pub list: bool,
    /// paper, cpu or smoke (see the manifest).
    #[arg(long, default_value = "cpu")]
    pub budget: String,
    /// Seeds per cell (default: the budget's). 0 would plan nothing and report an empty table.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=1000))]
    pub seeds: Option<u32>,
    /// Runs at once; each gets cores / jobs libtorch threads unless --threads is given. Default:
    /// one per core on the CPU, 2 on a GPU (both measured fastest).
    #[arg(long, value_parser = count(1, 1024))]
    pub jobs: Option<usize>,
    /// libtorch threads per run.
    #[arg(long, value_parser = count(1, 1024))]
    pub threads: Option<usize>,
    #[arg(long, default_value = "auto")]
    pub device: pdt_base::device::DeviceSpec,
    /// Each run's run.matmul: the model's products in `fp32`, `tf32` (CUDA) or `bf16` (mixed
    /// precision where the hardware has native bf16; experimental) (part of a run's
    /// identity; docs/implementation-details.md, C.8).
    #[arg(long, default_value = "fp32")]
    pub matmul: pdt_base::device::Matmul,
    /// Output directory: data/, runs/, configs/, logs/, reports/.
    #[arg(long, default_value = "runs/repro")]
    pub out: PathBuf,
    /// Where the datasets go (default: <out>/data).
    #[arg(long)]
    pub data_root: Option<PathBuf>,
    /// Directory with the committed agents (`<env>/agent.json`) that collect the datasets
    /// (default: `pretrained` here, else the `pretrained/` of the checkout promptdt was built in).
    #[arg(long)]
    pub pretrained_root: Option<PathBuf>,
    /// The reference release's prompt files (`official-prompts/`): its experts' returns, which
    /// normalise the paper's numbers, are recomputed from them (default: the numbers committed in
    /// the manifest, made from the same files).
    #[arg(long)]
    pub reference: Option<PathBuf>,
    /// `jobs`: write one command per run (jobs.txt) and a Slurm array script instead of running.
    #[arg(long)]
    pub emit: Option<String>,
    /// Only write the report, from the run directories as they are (and, for a run whose
    /// directory is absent, its archive in --registry).
    #[arg(long)]
    pub report_only: bool,
    /// Print where each run stands (finished, archived, part-way, not started) and the command
    /// that goes on; runs and writes nothing.
    #[arg(long, conflicts_with_all = ["report_only", "emit", "only", "list"])]
    pub status: bool,
    /// The results registry `--report-only` and `--status` read archived runs from.
    #[arg(long, default_value = "results")]
    pub registry: PathBuf,
    /// Run only this run (`<cell>/<budget>/seed<N>`, as jobs.txt names it), or these runs
    /// (comma-separated), and write no report.
    #[arg(long)]
    pub only: Option<String>,
    /// Train up to N runs of one family (one model shape, device and data; not MACAW) as one
    /// pack, in one process (docs/packs.md); a pack counts as one of --jobs. With `--emit jobs`,
    /// one job per pack. Default: 12 on a GPU, 1 (each run its own process) on the CPU.
    #[arg(long, value_parser = count(1, 1024))]
    pub pack: Option<usize>,
    /// The engine of the packs (docs/packs.md): `batched` (one batched computation for the pack,
    /// within a tolerance of solo training; the default on a GPU) or `solo` (each run exactly as
    /// alone, one run after another; the default on the CPU).
    #[arg(long, value_parser = ["batched", "solo"])]
    pub pack_engine: Option<String>,
    /// OMP_WAIT_POLICY for the runs (PASSIVE or ACTIVE).
    #[arg(long, default_value = "PASSIVE")]
    pub omp_wait_policy: String,
}

#[derive(Debug, Subcommand)]
pub enum DataCommand {
    /// Per file: trajectories, steps, dims, dtypes, returns (a table, or JSON with --json).
    Inspect(InspectArgs),
    /// Convert the reference release's pickles (`*.pkl`) into the native format.
    Convert(ConvertArgs),
    /// Dataset quality: return per task and mode against the reference, with the quality bars.
    Report(DataReportArgs),
    /// A flat `.npz` of step arrays with a `task_ids` column into per-task datasets and prompt
    /// sets of a task suite (or family), all checked before anything is written.
    Import(ImportArgs),
}

#[derive(Debug, Args)]
pub struct DataReportArgs {
    /// A dataset directory written by `promptdt collect` (`{env}-{task}-{mode}.safetensors`).
    pub ours: PathBuf,
    /// Directory of reference files (the reference release's pickles, or native files).
    #[arg(long)]
    pub reference: Option<PathBuf>,
    /// Output directory (default: <OURS>/report).
    #[arg(long)]
    pub out: Option<PathBuf>,
}

#[derive(Debug, Args)]
pub struct InspectArgs {
    /// A dataset file (.pkl or .safetensors) or a directory of them. In a directory, an entry
    /// named like a data file that is not one (a symbolic link loop, a dangling link) is an error
    /// naming it and why.
    pub path: PathBuf,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Args)]
pub struct ImportArgs {
    /// The family the data are of: a task suite file (`suite.toml`) or a built-in family's name.
    #[arg(long)]
    pub env: String,
    /// A flat `.npz` of step arrays: observations [N, obs_dim], actions [N, act_dim], rewards
    /// [N], terminals [N], timeouts [N], task_ids [N] (what `promptdt.flat_dataset` holds).
    #[arg(long, group = "source", required_unless_present_any = ["hdf5", "minari"])]
    pub npz: Option<PathBuf>,
    /// A flat HDF5 file of the same arrays (D4RL's layout: the step arrays at the root; other
    /// datasets in it are listed and left out), read without libhdf5.
    #[arg(long, group = "source")]
    pub hdf5: Option<PathBuf>,
    /// A Minari dataset id: read by the `minari` library in a Python with `promptdt` (the suite's
    /// `[environment] python`, else `$PROMPTDT_PYTHON`, else `python3`).
    #[arg(long, group = "source")]
    pub minari: Option<String>,
    /// Where each step's (or Minari episode's) task is: for `--npz`/`--hdf5` the array of task
    /// indices (default `task_ids`; an HDF5 path such as `infos/task`); for `--minari` the key of
    /// the episodes' reset options or infos holding a task index or name (default `task`).
    #[arg(long)]
    pub task_field: Option<String>,
    /// `--minari` only: every episode is of this task (an index, or a suite task's name).
    #[arg(long, requires = "minari")]
    pub task: Option<String>,
    /// Output directory for `{name}-{task}-{mode}.safetensors` and its prompt sets.
    #[arg(long)]
    pub out: PathBuf,
    /// The datasets' mode (`expert`, `medium`, ...): files `{name}-{task}-{mode}` and
    /// `{name}-{task}-prompt-{mode}`.
    #[arg(long, default_value = "expert")]
    pub mode: String,
    /// How each task's prompt set is made from its data: `best:N`, its N highest-return episodes.
    #[arg(long, default_value = "best:5")]
    pub prompt_rule: String,
}

#[derive(Debug, Args)]
pub struct ConvertArgs {
    /// Directory holding `{env}-{task}-{mode}.pkl` files.
    pub src: PathBuf,
    /// Output directory for `{env}-{task}-{mode}.safetensors`.
    pub dst: PathBuf,
}

#[derive(Debug, Subcommand)]
pub enum AgentCommand {
    /// Per-task experts: for every task, the best of the given snapshots (and the base expert),
    /// re-evaluated on a few episodes; writes an agent directory for `collect --from-pretrained
    /// --pretrained-dir`.
    Combine(CombineArgs),
}

#[derive(Debug, Args)]
pub struct CombineArgs {
    /// A finished agent directory (a run's `agent/`, or `pretrained/<env>`): its expert is a
    /// candidate, its medium policy is kept.
    #[arg(long)]
    pub base: PathBuf,
    /// Snapshot directories (a run's `snapshots/`) or policy files, comma-separated.
    #[arg(long, value_delimiter = ',', required = true)]
    pub snapshots: Vec<PathBuf>,
    /// Output agent directory.
    #[arg(long)]
    pub out: PathBuf,
    /// Snapshots re-evaluated per task (the best by their recorded evaluation).
    #[arg(long, default_value_t = 3)]
    pub top_k: usize,
    /// Deterministic evaluation episodes per task and snapshot.
    #[arg(long, default_value_t = 5)]
    pub eval_episodes: usize,
    /// Do not try mirrored snapshots (Ant-Dir: each snapshot also acting through the body's two
    /// reflections, towards the mirror images of the directions it walks well towards).
    #[arg(long)]
    pub no_mirrors: bool,
    /// Record in the agent that its datasets are written without exploration noise (what
    /// `collect --from-pretrained` then does unless given --explore).
    #[arg(long)]
    pub deterministic_datasets: bool,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    #[arg(long, default_value = "cpu")]
    pub device: DeviceSpec,
}

#[derive(Debug, Subcommand)]
pub enum ModelCommand {
    /// Predict actions for a batch stored in safetensors (tensor names: docs/model-forward.md).
    Forward(ForwardArgs),
}

#[derive(Debug, Args)]
pub struct ForwardArgs {
    /// Weights with the reference state_dict names (safetensors).
    #[arg(long)]
    pub weights: PathBuf,
    /// Input batch (safetensors).
    #[arg(long)]
    pub inputs: PathBuf,
    /// Where to write `action_preds` (safetensors).
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long, default_value = "cpu")]
    pub device: DeviceSpec,
    /// Intra-op threads of libtorch (default: all cores). Bit-for-bit comparisons with PyTorch need
    /// the thread count PyTorch ran with (the golden fixtures: 1).
    #[arg(long, value_parser = count(1, 1024))]
    pub threads: Option<usize>,
    /// Attention heads, for weights that do not record them (a PyTorch state_dict export; the
    /// reference model has 1). promptdt's checkpoints record it.
    #[arg(long)]
    pub n_head: Option<usize>,
}

#[derive(Debug, Args)]
pub struct DemoArgs {
    /// Seeds per method (the closing numbers in the README use 3).
    #[arg(long, default_value_t = 1)]
    pub seeds: u64,
    /// Override train.iterations of configs/point_robot/demo.toml.
    #[arg(long)]
    pub iterations: Option<u64>,
    /// Where data, runs and the report go.
    #[arg(long, default_value = "runs/demo")]
    pub out: PathBuf,
    #[arg(long, default_value = "auto")]
    pub device: DeviceSpec,
    /// Only the old smoke check: a few training steps on synthetic data.
    #[arg(long)]
    pub smoke: bool,
}

#[derive(Debug, Args)]
pub struct CollectArgs {
    /// Task family: `point_robot`, `metaworld_reach`, `dial` (scripted policies), `cheetah_dir`,
    /// `cheetah_vel`, `ant_dir` (trains an RL agent, then writes its datasets), or a task suite
    /// file (`path/suite.toml`, with --policy: played in its [environment] by the Python worker).
    #[arg(long)]
    pub env: String,
    /// Task suites: the expert policy, a Python `module:callable` called as `policy(obs, task)`
    /// in the worker (the suite file's directory is on its path) returning one action; the medium
    /// level is the expert with --medium-noise, the random level uniform actions in the bounds
    /// (docs/your-own-tasks.md).
    #[arg(long, value_name = "MODULE:CALLABLE")]
    pub policy: Option<String>,
    /// Task suites: a second policy for the medium level (with --action-noise), instead of the
    /// expert with --medium-noise.
    #[arg(
        long,
        value_name = "MODULE:CALLABLE",
        requires = "policy",
        conflicts_with = "medium_noise"
    )]
    pub medium_policy: Option<String>,
    /// Task suites: standard deviation of the Gaussian noise on the expert's actions that makes
    /// the medium level, in half-ranges of each action dimension (default 0.5).
    #[arg(long, requires = "policy")]
    pub medium_noise: Option<f64>,
    /// Task suites: environments per task stepped together in the worker (default 10); the data
    /// does not depend on it.
    #[arg(long, requires = "policy", value_parser = count(1, 10_000))]
    pub envs_per_task: Option<usize>,
    /// Output directory of the datasets (default: data/<env>).
    #[arg(long)]
    pub out: Option<PathBuf>,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Episodes per task in each main dataset, 1 to 100000 (default: 200 for metaworld_reach and
    /// dial, the paper's count; 100 otherwise).
    #[arg(long, value_parser = count(1, 100_000))]
    pub episodes: Option<usize>,
    /// Scripted families and task suites: which datasets to write (default
    /// `expert,medium,random`).
    #[arg(long, value_delimiter = ',')]
    pub modes: Option<Vec<String>>,
    /// metaworld_reach: standard deviation of the expert's (and medium policy's) Gaussian
    /// action noise, 0 to 10 (default 0.2, Meta-World's test-harness noise; 0 = the deterministic
    /// expert, every episode of a task the same). Task suites: the noise on --policy's (and
    /// --medium-policy's) actions, in half-ranges of each action dimension (default 0).
    #[arg(long)]
    pub action_noise: Option<f64>,
    /// Episodes per task in each prompt set (1 to 10000); task suites: the prompt set is that
    /// many of the dataset's episodes of highest return (the rule `best:N` of `data import`).
    #[arg(long, default_value_t = 5, value_parser = count(1, 10_000))]
    pub prompt_episodes: usize,
    /// Skip training: write the datasets from the committed agent (pretrained/<env>, or
    /// --pretrained-dir).
    #[arg(long)]
    pub from_pretrained: bool,
    /// The agent directory --from-pretrained reads (`agent.json`, `expert.safetensors`,
    /// `medium.safetensors`).
    #[arg(long, requires = "from_pretrained")]
    pub pretrained_dir: Option<PathBuf>,
    /// RL run directory: checkpoints, snapshots, and the trained agent in `agent/`
    /// (default: runs/collect-<env>).
    #[arg(long)]
    pub run_dir: Option<PathBuf>,
    /// Continue the interrupted training in --run-dir from its last checkpoint.
    #[arg(long)]
    pub resume: bool,
    /// `sac` or `td3` (default: the paper's choice for the family).
    #[arg(long)]
    pub algorithm: Option<String>,
    /// Environment steps of RL training (default: the family's preset).
    #[arg(long)]
    pub steps: Option<u64>,
    /// Uniform random steps before learning starts (default: min(5000, steps / 4)).
    #[arg(long)]
    pub learning_starts: Option<u64>,
    /// Hidden layer sizes of actor and critics, e.g. `256,256`.
    #[arg(long, value_delimiter = ',')]
    pub hidden: Option<Vec<i64>>,
    #[arg(long)]
    pub batch_size: Option<usize>,
    /// Checkpoint every this many environment steps (at the next episode end).
    #[arg(long)]
    pub checkpoint_every: Option<u64>,
    /// Train on these tasks only (e.g. `--tasks 3` for a per-task agent); default all. With
    /// --resume: go on training on these tasks only (fine-tuning on the tasks it does worst).
    /// Scripted families: collect these tasks only (default: point robot all 40, metaworld_reach
    /// the paper's 20, tasks 1 to 20, dial all 10 digits); task suites: by index (default all).
    #[arg(long, value_delimiter = ',')]
    pub tasks: Option<Vec<usize>>,
    /// Minibatches from the most recent N transitions only (0: the whole replay buffer); with
    /// --resume --tasks, this makes fine-tuning learn from the fine-tuned tasks' transitions.
    #[arg(long)]
    pub sample_recent: Option<u64>,
    /// Write the datasets without exploration noise (default: what the agent's `agent.json` asks
    /// for in `dataset_noise`, else the policy's own noise, as in a replay buffer).
    #[arg(long, conflicts_with = "explore")]
    pub deterministic: bool,
    /// Write the datasets with the policy's own exploration noise, whatever the agent asks for.
    #[arg(long)]
    pub explore: bool,
    /// Intra-op threads of libtorch (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    #[arg(long, default_value = "cpu")]
    pub device: DeviceSpec,
    /// Stop training after this many environment steps of this invocation, leaving a resumable
    /// checkpoint (to test interruption).
    #[arg(long, hide = true)]
    pub stop_after: Option<u64>,
}

#[derive(Debug, Args)]
pub struct TrainArgs {
    /// Experiment file (TOML; see configs/). Not with --resume (the run's config.toml is used).
    #[arg(long, required_unless_present_any = ["resume", "pack"], conflicts_with = "resume")]
    pub config: Option<PathBuf>,
    /// Run directory to write (with --pack: the pack directory, holding one run directory per
    /// experiment file).
    #[arg(long, conflicts_with = "resume")]
    pub out: Option<PathBuf>,
    /// Continue the (killed) run in this directory from its last checkpoint, or the (killed) pack
    /// in this pack directory (each of its runs). With it, only --iterations (to extend the run),
    /// --device and --data (the same data, moved) may be given, and --engine for a pack.
    #[arg(long, conflicts_with_all = ["seed", "method", "macaw_preset"])]
    pub resume: Option<PathBuf>,
    /// Train a pack: the runs of these experiment files in lockstep in one process on one device
    /// (one environment family, one [model] shape and device; the Prompt-DT variants; MACAW trains
    /// alone), each into its own run directory in --out. See docs/packs.md.
    #[arg(
        long,
        num_args = 1..,
        value_name = "CONFIG",
        requires = "out",
        conflicts_with_all = ["config", "resume", "seed", "method", "macaw_preset"]
    )]
    pub pack: Vec<PathBuf>,
    /// The engine that steps a pack: `batched` (one batched computation) or `solo` (each run's own
    /// step, exactly as alone, one run after another). Default: solo on the CPU, batched on a GPU;
    /// a resumed pack keeps its engine.
    #[arg(long, value_parser = ["batched", "solo"])]
    pub engine: Option<String>,
    /// Accepted for old scripts: a pack's runs always evaluate apart, each with its own model
    /// (`together` is accepted with a note; docs/packs.md says why it went).
    #[arg(long, value_parser = ["together", "apart"], hide = true)]
    pub pack_eval: Option<String>,
    /// Stop after this many iterations of this invocation, leaving a resumable run (to test
    /// interruption).
    #[arg(long, hide = true)]
    pub stop_after_iterations: Option<u64>,
    /// Override run.seed.
    #[arg(long)]
    pub seed: Option<u64>,
    /// Override train.iterations; with --resume, extend the run to this many.
    #[arg(long)]
    pub iterations: Option<u64>,
    /// Override run.method (the list: `Method::ALL`, so help never misses a method).
    #[arg(long, help = method_help())]
    pub method: Option<String>,
    /// MACAW: replace the [macaw] section with a preset: `official` (the official
    /// standard.json) or `promptdt` (the Prompt-DT paper's table: width 300, the last 20k steps
    /// per task, adaptation on K* transitions with 10 steps). Every row stays a named option.
    #[arg(long, value_enum)]
    pub macaw_preset: Option<MacawPresetArg>,
    /// Override run.device (with --resume: for this invocation).
    #[arg(long)]
    pub device: Option<DeviceSpec>,
    /// Override run.matmul: the model's products in `fp32`, `tf32` (CUDA) or `bf16` (mixed
    /// precision where the hardware has native bf16; experimental) (docs/
    /// implementation-details.md, C.8). Not with --resume: a run keeps its own.
    #[arg(long, conflicts_with = "resume")]
    pub matmul: Option<pdt_base::device::Matmul>,
    /// Override data.dir; with --resume, where the run's data moved (their content must be the
    /// same: the run recorded a fingerprint).
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
}

#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum MacawPresetArg {
    Official,
    Promptdt,
}

#[derive(Debug, Args)]
pub struct EvalArgs {
    /// Run directory.
    #[arg(long)]
    pub run: PathBuf,
    /// Episodes per task (default: the run's eval.episodes; 1 to 10000).
    #[arg(long, value_parser = count(1, 10_000))]
    pub episodes: Option<usize>,
    /// `test` (held-out tasks) or `train`.
    #[arg(long, default_value = "test")]
    pub split: String,
    #[arg(long)]
    pub device: Option<DeviceSpec>,
    /// Where the run's data moved (their content must be what the run trained on).
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// The --adapt adaptation's iterations per task (default: the run's: [eval.adapt]'s steps,
    /// macaw.adapt_steps, eval.finetune_steps). Without --adapt (the older form, with a note):
    /// the run's own adaptation's (MACAW, MT-BC-Finetune).
    #[arg(long, value_parser = count(1, 1000))]
    pub adapt_steps: Option<usize>,
    /// The --adapt adaptation's batch: demonstration segments per iteration, MACAW's
    /// transitions per task (default: the run's).
    #[arg(long, value_parser = count(2, 1_000_000))]
    pub adapt_batch: Option<usize>,
    /// Test-time prompt strategy (docs/prompt-control.md): reference (default: the run's
    /// [eval.prompt], reference unless set), random-segment, best-return, nearest-start, bandit.
    /// Other than the default, results go to eval_prompt_<strategy>.json with the choices made.
    #[arg(long, value_parser = prompt_strategy)]
    pub prompt_strategy: Option<pdt_prompt::PromptStrategyKind>,
    /// Test-time prompt segments J (default: the run's sampler.prompt_episodes).
    #[arg(long, value_parser = count(1, 1000))]
    pub prompt_episodes: Option<usize>,
    /// Test-time steps per prompt segment H (default: the run's prompt length).
    #[arg(long, value_parser = count(1, 100_000))]
    pub prompt_length: Option<usize>,
    /// nearest-start and bandit: candidate segments start every this many steps (default: 1 for
    /// nearest-start, H for bandit).
    #[arg(long, value_parser = count(1, 100_000))]
    pub prompt_stride: Option<usize>,
    /// bandit: `epsilon-greedy` (default, as the bandit paper) or `ucb`.
    #[arg(long, value_parser = bandit_rule)]
    pub bandit_rule: Option<pdt_prompt::BanditRule>,
    /// bandit: exploration probability of epsilon-greedy at the first round (default 0.1, this
    /// project's setting; the cited code's is 1.0, with --bandit-explore-fraction 0.2).
    #[arg(long)]
    pub bandit_epsilon: Option<f64>,
    /// bandit: subtracted from epsilon after every round (default 0).
    #[arg(long)]
    pub bandit_epsilon_decay: Option<f64>,
    /// bandit: epsilon falls linearly to 0 over this share of the task's rounds (the cited
    /// code's schedule: 0.2, with --bandit-epsilon 1 and --prompt-stride 1); replaces
    /// --bandit-epsilon-decay.
    #[arg(long)]
    pub bandit_explore_fraction: Option<f64>,
    /// bandit: episodes per task in one round, between updates (default 1).
    #[arg(long, value_parser = count(1, 10_000))]
    pub bandit_round: Option<usize>,
    /// Repeats the evaluation over this many independent prompt draws and reset seeds (repeat 0
    /// is the evaluation without the flag; repeat r > 0 draws from its own stream of the run's
    /// seed, docs/run-directory.md), and writes each repeat's per-task returns and the spread
    /// over repeats (evaluation noise, apart from seed noise) beside the usual fields. Default 1:
    /// one evaluation, the file as before.
    #[arg(long, value_parser = count(1, 1000), default_value_t = 1)]
    pub repeats: usize,
    /// Evaluation-time adaptation: --adapt and its settings.
    #[command(flatten)]
    pub adaptation: AdaptFlags,
}

#[derive(Debug, Args)]
pub struct ReportArgs {
    /// Run directories (or directories holding them).
    #[arg(required = true)]
    pub runs: Vec<PathBuf>,
    /// Output directory for table.md/csv and curves_<env>.png/svg/csv.
    #[arg(long, default_value = "report")]
    pub out: PathBuf,
    #[arg(long)]
    pub title: Option<String>,
}

#[derive(Debug, Subcommand)]
pub enum EnvCommand {
    /// Replay an initial state and actions through a MuJoCo environment (format: docs/mujoco-envs.md;
    /// metaworld_reach: docs/metaworld-reach.md; dial: docs/dial.md).
    Replay(ReplayArgs),
}

#[derive(Debug, Args)]
pub struct ReplayArgs {
    /// Family: cheetah_dir, cheetah_vel, ant_dir, metaworld_reach, dial or point_robot.
    #[arg(long)]
    pub env: String,
    /// Task index within the family.
    #[arg(long)]
    pub task: usize,
    /// JSON `{"qpos": [...], "qvel": [...]}` (cheetah 9 + 9, ant 15 + 14 values). Not for
    /// metaworld_reach and point_robot, whose episodes start from the task's reset state. dial:
    /// optional `{"qpos": [9 joint angles]}`, a start pose settled back as collection episodes
    /// start (default: the deterministic reset).
    #[arg(long)]
    pub init: Option<PathBuf>,
    /// JSON array of actions, one array per step.
    #[arg(long)]
    pub actions: PathBuf,
    /// Output JSON: observations, rewards, terminated, truncated.
    #[arg(long)]
    pub out: PathBuf,
}

/// A clap parser for a count in `lo..=hi`: sizes that could not be allocated (or would spend
/// minutes spawning threads) are refused with the allowed range, before anything starts.
fn count(lo: usize, hi: usize) -> impl Fn(&str) -> Result<usize, String> + Clone {
    move |s: &str| {
        let n: usize = s.trim().parse().map_err(|e| format!("`{s}` is not a count: {e}"))?;
        if (lo..=hi).contains(&n) {
            Ok(n)
        } else {
            Err(format!("must be between {lo} and {hi}, got {n}"))
        }
    }
}

/// `--method`'s help: every method's name, from `Method::ALL`.
fn method_help() -> String {
    let names: Vec<&str> = pdt_rundir::config::Method::ALL.iter().map(|m| m.name()).collect();
    format!("Override run.method ({})", names.join(", "))
}
