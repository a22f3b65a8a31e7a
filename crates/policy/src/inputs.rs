//! What a policy accepts as input: the bound on returns, the f32 check, and the record of the
//! largest input of a step (named when an action comes out not finite). Below both the policy
//! (`policy.rs`, which builds a step's inputs) and the episode (`episode.rs`, which keeps them).

use crate::PolicyError;

/// The largest return and return-to-go accepted (raw, in reward units), as the data readers accept
/// returns-to-go (`docs/failure-behaviour.md`): returns are f32 tokens, and beyond this they
/// overflow in the model's arithmetic.
pub const MAX_RETURN: f64 = 1e30;

/// `values` as f32, refusing what is not finite there (a huge f64 becomes an f32 infinity).
pub(crate) fn finite_f32(name: &str, values: &[f64]) -> Result<Vec<f32>, PolicyError> {
    values
        .iter()
        .enumerate()
        .map(|(i, &x)| {
            let y = x as f32;
            if y.is_finite() {
                Ok(y)
            } else {
                Err(PolicyError::Input(format!("{name}[{i}] = {x:e} is not a finite f32")))
            }
        })
        .collect()
}

/// The model inputs of one step, kept by magnitude: when the policy's action comes out NaN or
/// infinite, the error names the input most likely at fault (the largest one fed to the model).
#[derive(Debug, Default, Clone)]
pub struct Inputs {
    /// The field and raw value, as given; the value the model sees.
    largest: Option<(String, f32)>,
}

impl Inputs {
    pub(crate) fn see(&mut self, field: impl FnOnce() -> String, model_value: f32) {
        let bigger = match &self.largest {
            Some((_, v)) => model_value.abs() > v.abs(),
            None => true,
        };
        if bigger {
            self.largest = Some((field(), model_value));
        }
    }

    pub(crate) fn describe(&self) -> String {
        match &self.largest {
            Some((field, v)) => {
                format!("its largest input is {field} ({v:e} as the model sees it)")
            }
            None => "no input stands out".into(),
        }
    }
}
