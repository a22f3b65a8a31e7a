//! MACAW's hyper-parameters, the `[macaw]` section of a MACAW run's configuration (spec 7 of
//! `macaw.md`); `pdt_macaw` acts on them and re-exports them.

use pdt_base::num::compact;
use serde::{Deserialize, Serialize};

/// A MACAW setting out of range; the message names the key.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("invalid MACAW configuration: {0}")]
pub struct InvalidMacaw(pub String);

/// Hidden-layer activation. The official code uses ReLU; the Prompt-DT paper's table says tanh
/// (spec 7.1, probably a mis-report): one flag away.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Activation {
    #[default]
    Relu,
    Tanh,
}

/// The order of the test-time adaptation steps when there are several (spec 5.5; the paper does
/// not say).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum AdaptOrder {
    /// All value steps, then all policy steps against the final value function (as the training
    /// inner loop does with `maml_steps > 1`).
    #[default]
    ValueFirst,
    /// Value step, policy step, value step, ...
    Interleaved,
}

/// The two configurations of spec 7.1.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Preset {
    /// `config/alg/standard.json` of the official code.
    Official,
    /// The Prompt-DT paper's "Hyperparameters of MACAW" table: width 300, each task's last 20k
    /// steps, adaptation on K* transitions with 10 steps; everything it does not list official.
    Promptdt,
}

impl Preset {
    pub fn name(self) -> &'static str {
        match self {
            Preset::Official => "official",
            Preset::Promptdt => "promptdt",
        }
    }
}

/// Every MACAW hyper-parameter; the defaults are the official `standard.json` (spec 7).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MacawConfig {
    /// MLP width (official 100; Prompt-DT table 300).
    pub width: usize,
    /// Hidden layers (3).
    pub depth: usize,
    pub hidden_activation: Activation,
    /// Keep each task's last `buffer_rows` transitions (0 = all; Prompt-DT table 20000).
    pub buffer_rows: usize,
    /// Then every `buffer_skip`-th of them (official 7).
    pub buffer_skip: usize,
    /// Store each episode in reverse time order, as the official buffer writer does (spec 2.2);
    /// matters only for the contiguous inner batches at episode boundaries.
    pub reverse_episodes: bool,
    /// Discount of the Monte-Carlo returns and bootstrap factors.
    pub discount: f64,
    /// Inner (adaptation) batch in training (256), drawn as one contiguous window when
    /// `contiguous_inner`.
    pub inner_batch: usize,
    pub contiguous_inner: bool,
    /// Outer batch in training (256), uniform without replacement.
    pub outer_batch: usize,
    /// Training tasks per meta-step (5; all of them when there are fewer).
    pub task_batch: usize,
    /// Initial values of the learned inner learning rates (the raw parameter is ln of it).
    pub inner_value_lr: f64,
    pub inner_policy_lr: f64,
    /// Outer Adam learning rates of V, pi, and of the raw inner learning rates and adv. coefficient.
    pub outer_value_lr: f64,
    pub outer_policy_lr: f64,
    pub lrlr: f64,
    /// Initial advantage-head coefficient (learned; spec 5.2).
    pub advantage_head_coef: f64,
    /// Fixed policy standard deviation (0.2).
    pub action_sigma: f64,
    /// AWR weights are exp(min(A_normalised, ln exp_advantage_clip)).
    pub exp_advantage_clip: f64,
    pub adaptation_temp: f64,
    /// Soft target of the outer value loss: 0.9 * phi + 0.1 * phi'.
    pub target_vf_alpha: f64,
    /// Test-time adaptation: transitions (official 256, Prompt-DT K*), uniform from the test task's
    /// dataset; gradient steps (official 1, Prompt-DT 10); their order.
    pub adapt_batch: usize,
    pub adapt_steps: usize,
    pub adapt_order: AdaptOrder,
}

impl Default for MacawConfig {
    fn default() -> Self {
        Self {
            width: 100,
            depth: 3,
            hidden_activation: Activation::Relu,
            buffer_rows: 0,
            buffer_skip: 7,
            reverse_episodes: true,
            discount: 0.99,
            inner_batch: 256,
            contiguous_inner: true,
            outer_batch: 256,
            task_batch: 5,
            inner_value_lr: 1e-3,
            inner_policy_lr: 1e-3,
            outer_value_lr: 1e-5,
            outer_policy_lr: 1e-4,
            lrlr: 1e-3,
            advantage_head_coef: 0.01,
            action_sigma: 0.2,
            exp_advantage_clip: 20.0,
            adaptation_temp: 1.0,
            target_vf_alpha: 0.9,
            adapt_batch: 256,
            adapt_steps: 1,
            adapt_order: AdaptOrder::ValueFirst,
        }
    }
}

impl MacawConfig {
    /// A preset; `prompt_length` is the environment's K* (the Prompt-DT table's evaluation batch).
    pub fn preset(preset: Preset, prompt_length: usize) -> Self {
        match preset {
            Preset::Official => Self::default(),
            // The rows of the Prompt-DT table that differ from standard.json (spec 7.1). Its
            // "activation tanh" row is left at ReLU (the official hidden activation; the table most
            // likely names the output squash): `hidden_activation = "tanh"` follows the table.
            Preset::Promptdt => Self {
                width: 300,
                buffer_rows: 20_000,
                adapt_batch: prompt_length,
                adapt_steps: 10,
                ..Self::default()
            },
        }
    }

    pub fn validate(&self) -> Result<(), InvalidMacaw> {
        let bad = |m: String| Err(InvalidMacaw(m));
        if self.width == 0 || self.depth == 0 {
            return bad(format!(
                "macaw.width = {} and macaw.depth = {} must be at least 1",
                self.width, self.depth
            ));
        }
        if self.width > 4096 {
            return bad(format!(
                "macaw.width = {} is above 4096 (the generator matrices grow as width^2 x 100)",
                self.width
            ));
        }
        if self.buffer_skip == 0 {
            return bad("macaw.buffer_skip must be at least 1".into());
        }
        if !(self.discount > 0.0 && self.discount <= 1.0) {
            return bad(format!("macaw.discount = {} must be in (0, 1]", compact(self.discount)));
        }
        // The AWR weights normalise by the batch's standard deviation: one row gives NaN (spec 4).
        for (name, v) in [
            ("inner_batch", self.inner_batch),
            ("outer_batch", self.outer_batch),
            ("adapt_batch", self.adapt_batch),
        ] {
            if v < 2 {
                return bad(format!("macaw.{name} = {v}: at least 2 (the advantages are normalised by their standard deviation)"));
            }
        }
        if self.task_batch == 0 {
            return bad("macaw.task_batch must be at least 1".into());
        }
        for (name, v) in [
            ("inner_value_lr", self.inner_value_lr),
            ("inner_policy_lr", self.inner_policy_lr),
            ("outer_value_lr", self.outer_value_lr),
            ("outer_policy_lr", self.outer_policy_lr),
            ("lrlr", self.lrlr),
            ("advantage_head_coef", self.advantage_head_coef),
            ("action_sigma", self.action_sigma),
            ("adaptation_temp", self.adaptation_temp),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return bad(format!("macaw.{name} = {} must be a positive number", compact(v)));
            }
        }
        if !(self.exp_advantage_clip.is_finite() && self.exp_advantage_clip > 1.0) {
            return bad(format!(
                "macaw.exp_advantage_clip = {} must be above 1",
                compact(self.exp_advantage_clip)
            ));
        }
        if !(0.0..=1.0).contains(&self.target_vf_alpha) {
            return bad(format!(
                "macaw.target_vf_alpha = {} must be in [0, 1]",
                compact(self.target_vf_alpha)
            ));
        }
        if self.adapt_steps > 1000 {
            return bad(format!("macaw.adapt_steps = {} is above 1000", self.adapt_steps));
        }
        Ok(())
    }
}
