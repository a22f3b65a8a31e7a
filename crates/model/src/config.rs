//! Model hyper-parameters. Defaults are the reference code's (`pdt_main.py` + HF `GPT2Config` 4.5.1
//! defaults; `promptdt-reference.md` a.1).

use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PromptDtConfig {
    /// Observation size (derived from the dataset, never set by hand in an experiment file).
    pub state_dim: usize,
    /// Action size (derived from the dataset).
    pub act_dim: usize,
    /// Width of every token embedding (`hidden_size`, 128).
    pub hidden_size: usize,
    /// Transformer blocks (3).
    pub n_layer: usize,
    /// Attention heads (1).
    pub n_head: usize,
    /// MLP inner width (`n_inner` = 4 * 128).
    pub n_inner: usize,
    /// Rows of the timestep embedding tables (`max_ep_len` = 1000 in `pdt_main.py`).
    pub max_ep_len: usize,
    /// Maximum tokens per sequence: 3 * (prompt steps + history steps) must not exceed it (1024).
    pub n_positions: usize,
    /// Residual dropout (`resid_pdrop`).
    pub resid_pdrop: f64,
    /// Attention-probability dropout (`attn_pdrop`).
    pub attn_pdrop: f64,
    /// Dropout on the input embeddings (`embd_pdrop`, HF default 0.1).
    pub embd_pdrop: f64,
    /// LayerNorm epsilon of the trunk (HF default 1e-5; `embed_ln` uses PyTorch's default, also 1e-5).
    pub layer_norm_epsilon: f64,
    /// Squash predicted actions with tanh (`action_tanh=True`).
    pub action_tanh: bool,
}

impl PromptDtConfig {
    /// The reference architecture for the given observation and action sizes.
    pub fn reference(state_dim: usize, act_dim: usize) -> Self {
        Self {
            state_dim,
            act_dim,
            hidden_size: 128,
            n_layer: 3,
            n_head: 1,
            n_inner: 512,
            max_ep_len: 1000,
            n_positions: 1024,
            resid_pdrop: 0.1,
            attn_pdrop: 0.1,
            embd_pdrop: 0.1,
            layer_norm_epsilon: 1e-5,
            action_tanh: true,
        }
    }

    /// The sizes that make the architecture, by name (as checkpoints record them).
    pub fn shape_fields(&self) -> [(&'static str, usize); 8] {
        [
            ("state_dim", self.state_dim),
            ("act_dim", self.act_dim),
            ("hidden_size", self.hidden_size),
            ("n_layer", self.n_layer),
            ("n_head", self.n_head),
            ("n_inner", self.n_inner),
            ("max_ep_len", self.max_ep_len),
            ("n_positions", self.n_positions),
        ]
    }

    /// Checks the sizes make a valid model.
    pub fn validate(&self) -> Result<(), String> {
        for (name, v) in self.shape_fields() {
            if v == 0 {
                return Err(format!("model.{name} must be at least 1"));
            }
        }
        if !self.hidden_size.is_multiple_of(self.n_head) {
            return Err(format!(
                "model.hidden_size ({}) must be divisible by model.n_head ({})",
                self.hidden_size, self.n_head
            ));
        }
        for (name, p) in [
            ("resid_pdrop", self.resid_pdrop),
            ("attn_pdrop", self.attn_pdrop),
            ("embd_pdrop", self.embd_pdrop),
        ] {
            if !(0.0..1.0).contains(&p) {
                return Err(format!("model.{name} must be in [0, 1), got {p}"));
            }
        }
        Ok(())
    }

    /// Parameter names in the reference's registration order (`model.parameters()`: the GPT-2 trunk
    /// first, then the embeddings, `embed_ln` and the heads). The order matters: gradient clipping
    /// sums the per-parameter norms in this order, and float addition is not associative.
    pub fn parameter_names(&self) -> Vec<String> {
        let mut names = vec!["transformer.wte.weight".to_string()];
        let wb = |prefix: &str| [format!("{prefix}.weight"), format!("{prefix}.bias")];
        for i in 0..self.n_layer {
            for m in ["ln_1", "attn.c_attn", "attn.c_proj", "ln_2", "mlp.c_fc", "mlp.c_proj"] {
                names.extend(wb(&format!("transformer.h.{i}.{m}")));
            }
        }
        names.extend(wb("transformer.ln_f"));
        for prefix in ["", "prompt_"] {
            names.push(format!("{prefix}embed_timestep.weight"));
            for m in ["embed_return", "embed_state", "embed_action"] {
                names.extend(wb(&format!("{prefix}{m}")));
            }
        }
        for m in ["embed_ln", "predict_state", "predict_action.0", "predict_return"] {
            names.extend(wb(m));
        }
        names
    }

    /// Number of trainable parameters (the unused `wte` and prediction heads included, as in the
    /// reference's `model.parameters()`).
    pub fn num_parameters(&self) -> usize {
        let (h, ds, da) = (self.hidden_size, self.state_dim, self.act_dim);
        let linear = |i: usize, o: usize| i * o + o;
        let embeddings = self.max_ep_len * h + linear(1, h) + linear(ds, h) + linear(da, h);
        let block = 2 * (2 * h)
            + linear(h, 3 * h)
            + linear(h, h)
            + linear(h, self.n_inner)
            + linear(self.n_inner, h);
        let trunk = h + self.n_layer * block + 2 * h;
        let heads = linear(h, ds) + linear(h, da) + linear(h, 1);
        2 * embeddings + 2 * h + trunk + heads
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parameter_count_matches_reference_arithmetic() {
        // promptdt-reference.md a.2: 862,619 (cheetah 20/6), 866,084 (ant 27/8), 869,164 (ML1 39/4).
        assert_eq!(PromptDtConfig::reference(20, 6).num_parameters(), 862_619);
        assert_eq!(PromptDtConfig::reference(27, 8).num_parameters(), 866_084);
        assert_eq!(PromptDtConfig::reference(39, 4).num_parameters(), 869_164);
    }

    #[test]
    fn validate_rejects_bad_sizes() {
        let mut c = PromptDtConfig::reference(20, 6);
        assert!(c.validate().is_ok());
        c.n_head = 3;
        assert!(c.validate().unwrap_err().contains("divisible"));
        let mut c = PromptDtConfig::reference(0, 6);
        assert!(c.validate().unwrap_err().contains("state_dim"));
        c.state_dim = 20;
        c.attn_pdrop = 1.0;
        assert!(c.validate().unwrap_err().contains("attn_pdrop"));
    }
}
