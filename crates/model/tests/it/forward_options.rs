//! `PromptDt::forward`'s options are independent of one another: each way of asking for the same
//! computation runs the same ops, bit for bit (the entry points they replaced were separate
//! functions, so this held by construction before; now it holds by these tests).
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use crate::support;
use pdt_model::dropout::{Dropout, DropoutMasks};
use pdt_model::prompt_dt::{Act, Prompt, Sequence, Steps};
use pdt_model::{LastBlock, PrefixCache, PromptDt, PromptDtConfig};
use support::segments;
use tch::{nn::VarStore, Device, Tensor};

fn bits(t: &Tensor) -> Vec<u32> {
    let v: Vec<f32> = t.flatten(0, -1).try_into().unwrap();
    v.iter().map(|f| f.to_bits()).collect()
}

#[test]
fn every_way_of_asking_for_a_pass_gives_its_bits() {
    let _g = pdt_testkit::process::libtorch(); // the process's generator
    tch::manual_seed(3);
    let cfg = PromptDtConfig { n_head: 2, ..PromptDtConfig::reference(5, 3) };
    let vs = VarStore::new(Device::Cpu);
    let mut model = PromptDt::new(&vs.root(), &cfg);
    let (b, k) = (4, 6);
    let history = segments(b, k, 5, 3);
    let prompt = segments(b, 3, 5, 3);
    let len = PromptDt::token_count(&history, Some(&prompt));
    let masks = DropoutMasks::draw(&cfg, b, len, Device::Cpu);
    tch::no_grad(|| {
        for dropout in [Dropout::Off, Dropout::Given(&masks)] {
            let all = model.forward(&history, Sequence::new(Some(&prompt), dropout).all_steps());
            assert_eq!(all.size(), vec![b, 3 + k, 3]);
            // The history's steps are the last K of every step's.
            let hist = model.forward(&history, Sequence::new(Some(&prompt), dropout));
            assert_eq!(hist.size(), vec![b, k, 3]);
            assert_eq!(bits(&hist), bits(&all.narrow(1, 3, k)));
            // The prompt as embedded tokens runs the same ops as the prompt as segments.
            let tokens = model.prompt_tokens(&prompt);
            let by_tokens = Sequence {
                prompt: Some(Prompt::Tokens(&tokens)),
                steps: Steps::All,
                ..Sequence::new(None, dropout)
            };
            assert_eq!(bits(&model.forward(&history, by_tokens)), bits(&all));
            // The last block asked for in the pass is the model's set one.
            let states = Sequence { last_block: Some(LastBlock::StateTokens), ..by_tokens };
            let asked = model.forward(&history, states);
            model.set_last_block(LastBlock::StateTokens);
            assert_eq!(bits(&asked), bits(&model.forward(&history, by_tokens)));
            model.set_last_block(LastBlock::AllTokens);
            // Different dropout masks are different passes (the test can fail).
            if matches!(dropout, Dropout::Given(_)) {
                let off = model.forward(&history, Sequence::eval(Some(&prompt)).all_steps());
                assert_ne!(bits(&off), bits(&all));
            }
        }
        // A prefix of the prompt as segments and as tokens is one cache: the same actions.
        let rows = Tensor::arange(b, (tch::Kind::Int64, Device::Cpu));
        let by_segments = model.prefix(&prompt, None).select(&rows);
        let by_tokens = model.prefix(&model.prompt_tokens(&prompt), None).select(&rows);
        let act = |c: &PrefixCache| model.forward(&history, Act { prompt: Some(c), lora: None });
        assert_eq!(bits(&act(&by_segments)), bits(&act(&by_tokens)));
        assert_eq!(act(&by_segments).size(), vec![b, 3]);
    });
}
