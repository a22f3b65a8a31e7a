//! `promptdt serve`: a run's prompted policy over HTTP+JSON until Ctrl-C.

use crate::args::ServeArgs;
use anyhow::Result;
use std::time::Duration;

pub fn serve(a: ServeArgs) -> Result<()> {
    // Who may use it, settled (and an exposed address without a token refused) before the run is
    // loaded.
    let (auth, generated) = a.auth()?;
    pdt_serve::auth::check(&a.listen, &auth)?;
    let run = pdt_policy::Policy::load(&a.run, a.device, a.data.as_deref())?;
    let opts = options(a, auth)?;
    let warning = pdt_serve::auth::exposure_warning(&opts.listen, &opts.auth);
    let server = pdt_serve::Server::start(run, opts)?;
    if let Some(w) = warning {
        eprintln!("{w}");
    }
    // The first line of output: clients (and tests) read the address from it; a generated token
    // is the second, shown this once.
    out!("listening on http://{}", server.addr);
    if let Some(token) = generated {
        out!("token: {token}");
    }
    use std::io::Write as _;
    let _ = std::io::stdout().flush();
    server.wait_for_ctrl_c()?;
    Ok(())
}

/// The server's options from the flags.
fn options(a: ServeArgs, auth: pdt_serve::Auth) -> Result<pdt_serve::ServeOptions> {
    Ok(pdt_serve::ServeOptions {
        listen: a.listen,
        max_episodes: a.max_episodes,
        max_batch: a.max_batch,
        batch_wait: Duration::from_millis(a.batch_wait_ms as u64),
        idle_timeout: Duration::from_secs(a.idle_timeout_s as u64),
        max_body_bytes: a.max_body_bytes,
        header_timeout: Duration::from_secs(a.header_timeout_s as u64),
        body_timeout: Duration::from_secs(a.body_timeout_s as u64),
        max_connections: a.max_connections,
        threads: a.threads,
        prompt_strategy: pdt_prompt::PromptStrategy {
            strategy: a.prompt_strategy.unwrap_or_default(),
            episodes: a.prompt_episodes,
            length: a.prompt_length,
            ..Default::default()
        },
        adapt: a.adaptation.to_config().map_err(anyhow::Error::msg)?,
        auth,
        ..Default::default()
    })
}
