//! `promptdt`: a thin shell over the library crates. Each subcommand is a module of `cmd` that
//! turns its arguments into a library call; errors are printed with their causes and give a
//! nonzero exit code.

/// `println!` that hands a failed write back as an error instead of panicking:
/// `promptdt reproduce --list | head` closes the pipe early, and `main` ends quietly on that.
macro_rules! out {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        writeln!(std::io::stdout().lock(), $($arg)*).map_err($crate::StdoutError)?
    }};
}

/// `print!` the same way as `out!` (no newline added).
macro_rules! out_inline {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        write!(std::io::stdout().lock(), $($arg)*).map_err($crate::StdoutError)?
    }};
}

mod args;
mod bench_args;
mod cmd;
mod eval_flags;
mod prompt_args;
mod results_args;
mod video;

use anyhow::Result;
use args::{AgentCommand, Cli, Command, DataCommand, EnvCommand, ModelCommand};
use clap::Parser;
use results_args::ResultsCommand;
use std::io::ErrorKind;
use std::process::ExitCode;

/// A write to standard output failed (see `out!`).
#[derive(Debug)]
pub struct StdoutError(pub std::io::Error);

impl std::fmt::Display for StdoutError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "writing to standard output: {}", self.0)
    }
}

impl std::error::Error for StdoutError {}

fn main() -> ExitCode {
    // Before any tensor exists: a large-batch training step otherwise spends much of its CPU
    // time faulting in and zero-filling pages the allocator gave back after the previous step
    // (pdt_model::host_memory; 4.4 s -> 2.8 s per step at batch 560). Results do not change.
    let _ = pdt_torch::host_memory::keep_freed_memory();
    let cli = Cli::parse();
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        // The reader of our standard output went away (`| head`): not an error of ours.
        Err(e)
            if e.downcast_ref::<StdoutError>()
                .is_some_and(|s| s.0.kind() == ErrorKind::BrokenPipe) =>
        {
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("error: {}", error_chain(&e));
            ExitCode::FAILURE
        }
    }
}

/// The error and its causes, `: `-separated. Library errors already include their cause in their
/// message (so `to_string()` is useful to library users); a cause whose text is already there is
/// not repeated.
fn error_chain(e: &anyhow::Error) -> String {
    let mut out = String::new();
    for cause in e.chain() {
        let text = cause.to_string();
        if !out.contains(&text) {
            if !out.is_empty() {
                out.push_str(": ");
            }
            out.push_str(&text);
        }
    }
    out
}

/// `--die-with-parent`: `reproduce` holds the write end of a pipe that is this process's standard
/// input and never writes to it. When `reproduce` dies, however it dies (even SIGKILL), the kernel
/// closes that end and the read here ends: stop, so no child outlives a killed sweep. Whatever this
/// process was writing is safe: every file goes through the atomic writer, and its temporaries
/// are removed on the next start (`docs/failure-behaviour.md`). (A pipe rather than
/// `prctl(PR_SET_PDEATHSIG)`: that needs unsafe code.)
fn die_with_parent() {
    std::thread::spawn(|| {
        use std::io::Read as _;
        let mut stdin = std::io::stdin().lock();
        let mut buf = [0_u8; 64];
        loop {
            match stdin.read(&mut buf) {
                Ok(0) => break,
                Ok(_) => {}
                Err(e) if e.kind() == ErrorKind::Interrupted => {}
                Err(_) => break,
            }
        }
        // Not `eprintln!`: standard error is often a pipe to the parent that died, and
        // `eprintln!` panics when the write fails, which would end this thread, not the process.
        use std::io::Write as _;
        let _ = writeln!(std::io::stderr(), "promptdt: the parent process is gone; stopping");
        std::process::exit(1);
    });
}

/// Parses nothing more and decides nothing: each subcommand to its module (`cmd`).
fn run(cli: Cli) -> Result<()> {
    if cli.die_with_parent {
        die_with_parent();
    }
    match cli.command {
        Command::Data(DataCommand::Inspect(a)) => cmd::data::inspect(&a),
        Command::Data(DataCommand::Convert(a)) => cmd::data::convert(&a),
        Command::Data(DataCommand::Report(a)) => cmd::data::report(&a),
        Command::Data(DataCommand::Import(a)) => cmd::data::import(&a),
        Command::Model(ModelCommand::Forward(a)) => cmd::model::forward(&a),
        Command::Agent(AgentCommand::Combine(a)) => cmd::agent::combine(&a),
        Command::Collect(a) => cmd::collect::collect(&a),
        Command::Train(a) if cmd::pack::is_pack(&a) => cmd::pack::train_pack(&a),
        Command::Train(a) => cmd::train::train(&a),
        Command::Eval(a) => cmd::eval::eval(&a),
        Command::Report(a) => cmd::report::report(&a),
        Command::Env(EnvCommand::Replay(a)) => cmd::env::replay(&a),
        Command::Reproduce(a) => cmd::reproduce::reproduce(&a),
        Command::Results(ResultsCommand::Add(a)) => cmd::results::add(&a),
        Command::Results(ResultsCommand::Render(a)) => cmd::results::render(&a),
        Command::Render(a) => cmd::render::render(a),
        Command::Serve(a) => cmd::serve::serve(a),
        Command::Bench(a) => cmd::bench::bench(&a),
        Command::Demo(a) if a.smoke => cmd::demo::smoke(&a),
        Command::Demo(a) => cmd::demo::demo(&a),
    }
}
