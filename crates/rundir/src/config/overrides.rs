//! What a front end may change in an experiment file before a run starts (`promptdt train`'s flags,
//! `promptdt.train`'s arguments), applied in one place, and the names derived from a configuration
//! (a run's name and default directory, MACAW's K*).

use super::macaw::{MacawConfig, Preset};
use super::{Method, TrainConfig};
use pdt_base::device::{DeviceSpec, Matmul};
use std::path::PathBuf;

/// The settings a front end overrides; `None` keeps the file's.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Overrides {
    pub seed: Option<u64>,
    pub iterations: Option<u64>,
    pub method: Option<Method>,
    /// Replaces the `[macaw]` section by a preset (its adaptation batch is the run's K*).
    pub macaw_preset: Option<Preset>,
    pub device: Option<DeviceSpec>,
    pub matmul: Option<Matmul>,
    pub data: Option<PathBuf>,
}

/// A method name that is none of [`Method`]'s.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{name}: expected {expected}", name = .0, expected = expected_methods())]
pub struct UnknownMethod(pub String);

/// "prompt-dt, ..., mt-bc-finetune or macaw", from [`Method::ALL`].
fn expected_methods() -> String {
    let names: Vec<&str> = Method::ALL.iter().map(|m| m.name()).collect();
    match names.split_last() {
        Some((last, rest)) if !rest.is_empty() => format!("{} or {last}", rest.join(", ")),
        _ => names.join(""),
    }
}

impl std::str::FromStr for Method {
    type Err = UnknownMethod;

    /// A method by its name in `config.toml` (`prompt-dt`, ..., `macaw`).
    fn from_str(s: &str) -> Result<Self, UnknownMethod> {
        Method::ALL.into_iter().find(|m| m.name() == s).ok_or_else(|| UnknownMethod(s.to_string()))
    }
}

impl TrainConfig {
    /// Applies `o`. `env_prompt_length` gives the environment's preset prompt length H for an env
    /// name (from `pdt_envs`, which this crate does not link); it is asked only for a MACAW preset,
    /// whose adaptation batch is K* = J x H ([`TrainConfig::prompt_steps`]). The method is set
    /// before the preset, the preset before nothing that reads it.
    pub fn apply<E>(
        &mut self,
        o: &Overrides,
        env_prompt_length: impl FnOnce(&str) -> Result<usize, E>,
    ) -> Result<(), E> {
        if let Some(s) = o.seed {
            self.run.seed = s;
        }
        if let Some(n) = o.iterations {
            self.train.iterations = n;
        }
        if let Some(m) = o.method {
            self.run.method = m;
        }
        if let Some(p) = o.macaw_preset {
            let h = env_prompt_length(&self.env.name)?;
            self.macaw = MacawConfig::preset(p, self.prompt_steps(h));
        }
        if let Some(d) = o.device {
            self.run.device = d;
        }
        if let Some(m) = o.matmul {
            self.run.matmul = m;
        }
        if let Some(d) = &o.data {
            self.data.dir.clone_from(d);
        }
        Ok(())
    }

    /// Steps in a task's prompt, J x H (MACAW's K*: the Prompt-DT protocol adapts MACAW on as many
    /// transitions), with `env_prompt_length` the environment preset's H, used when
    /// `sampler.prompt_length` is not set.
    pub fn prompt_steps(&self, env_prompt_length: usize) -> usize {
        self.sampler.prompt_episodes * self.sampler.prompt_length.unwrap_or(env_prompt_length)
    }

    /// A run's name, `<method>-<env>-seed<seed>` (`run.json`'s `name`), with `env` the family's name.
    pub fn run_name(&self, env: &str) -> String {
        format!("{}-{}-seed{}", self.run.method.name(), env, self.run.seed)
    }

    /// Where `promptdt train` puts a run given no `--out`: `runs/<method>-<env>-seed<seed>`.
    pub fn default_run_dir(&self) -> PathBuf {
        PathBuf::from("runs").join(self.run_name(&self.env.name))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_method_parses_from_the_name_its_files_carry() {
        for m in Method::ALL {
            assert_eq!(m.name().parse::<Method>(), Ok(m));
            // `config.toml` and `run.json` spell it through serde: the same name.
            assert_eq!(serde_json::to_value(m).unwrap(), serde_json::json!(m.name()));
        }
        let e = "dt".parse::<Method>().unwrap_err();
        assert_eq!(
            e.to_string(),
            "dt: expected prompt-dt, prompt-mt-bc, mt-orl, mt-bc-finetune or macaw"
        );
    }

    #[test]
    fn overrides_apply_and_the_preset_takes_the_runs_k_star() {
        let mut c = TrainConfig::default();
        c.sampler.prompt_episodes = 2;
        let o = Overrides {
            seed: Some(7),
            iterations: Some(3),
            method: Some("macaw".parse().unwrap()),
            macaw_preset: Some(Preset::Promptdt),
            device: Some(DeviceSpec::Cuda),
            matmul: Some(Matmul::Tf32),
            data: Some(PathBuf::from("/d")),
        };
        let mut asked = None;
        c.apply(&o, |env| {
            asked = Some(env.to_string());
            Ok::<_, String>(5)
        })
        .unwrap();
        assert_eq!(asked.as_deref(), Some("point_robot"));
        assert_eq!((c.run.seed, c.train.iterations, c.run.method), (7, 3, Method::Macaw));
        assert_eq!((c.run.device, c.data.dir.clone()), (DeviceSpec::Cuda, PathBuf::from("/d")));
        assert_eq!(c.run.matmul, Matmul::Tf32);
        assert_eq!(c.macaw, MacawConfig::preset(Preset::Promptdt, 10));
        assert_eq!(c.macaw.adapt_batch, 10);
        assert_eq!(c.default_run_dir(), PathBuf::from("runs/macaw-point_robot-seed7"));

        // No preset: the environment is not asked (an unknown one fails later, by name).
        let mut d = TrainConfig::default();
        d.apply(&Overrides::default(), |_| Err("asked")).unwrap();
        assert_eq!(d, TrainConfig::default());
        let e = "nope".parse::<Method>().unwrap_err().to_string();
        assert!(e.contains("nope: expected prompt-dt"), "{e}");
    }
}
