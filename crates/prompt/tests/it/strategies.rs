//! Each prompt strategy picks a known segment in a known case.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use pdt_data::{TaskData, TaskDataset, TaskId, Trajectory};
use pdt_prompt::bandit::SegmentBandit;
use pdt_prompt::strategy::check_fits;
use pdt_prompt::{
    BanditConfig, BatchSampler, PromptStrategy, PromptStrategyKind, Rng, SamplerConfig,
    SegmentChoice, StateNorm,
};
use rand::SeedableRng;

/// Demonstration `i` has states `(i, t)` at step t (2 dims) and return `returns[i]`.
fn task(returns: &[f32], len: usize) -> TaskData {
    let trajs: Vec<Trajectory> = returns
        .iter()
        .enumerate()
        .map(|(i, &ret)| {
            let obs = (0..len).flat_map(|t| [i as f32, t as f32]).collect();
            let mut rew = vec![0.0; len];
            rew[len - 1] = ret;
            Trajectory::new(2, 1, obs, vec![0.0; len], rew, vec![false; len], vec![false; len])
                .unwrap()
        })
        .collect();
    let ds = TaskDataset::new(trajs).unwrap();
    TaskData { id: TaskId { env: "toy".into(), index: 0 }, dataset: ds.clone(), prompts: ds }
}

fn sampler<'a>(t: &'a TaskData, j: usize, h: usize, norm: StateNorm) -> BatchSampler<'a> {
    let cfg = SamplerConfig {
        k: 5,
        prompt_episodes: j,
        prompt_length: h,
        ..SamplerConfig::reference(1.0, 1000)
    };
    BatchSampler::new(cfg, &[t], norm, 1024).unwrap()
}

#[test]
fn names_parse_and_unknown_names_are_refused_with_the_list() {
    for k in PromptStrategyKind::ALL {
        assert_eq!(k.name().parse::<PromptStrategyKind>().unwrap(), k);
        assert_eq!(PromptStrategy::named(k.name()).unwrap().strategy, k);
    }
    let e = "tail".parse::<PromptStrategyKind>().unwrap_err().to_string();
    assert!(e.contains("`tail`") && e.contains("nearest-start"), "{e}");
    assert!(PromptStrategy::default().is_default());
    assert_eq!(PromptStrategy::default().strategy, PromptStrategyKind::Reference);
}

#[test]
fn best_return_picks_the_highest_return_demonstration_at_the_tail() {
    let t = task(&[3.0, 9.0, 1.0, 7.0], 30);
    let s = sampler(&t, 1, 5, StateNorm::identity(2));
    assert_eq!(s.best_return_segments(0), vec![SegmentChoice { demo: 1, start: 24 }]);
    let s2 = sampler(&t, 3, 5, StateNorm::identity(2));
    let demos: Vec<usize> = s2.best_return_segments(0).iter().map(|c| c.demo).collect();
    assert_eq!(demos, vec![1, 3, 0]);
    // the prompt holds demonstration 1's steps 24..28, with its returns-to-go (9 / scale 1)
    let p = s.prompt_from_choices(0, &s.best_return_segments(0)).unwrap();
    assert_eq!(p.timesteps, vec![24, 25, 26, 27, 28]);
    assert_eq!(&p.states[..2], &[1.0, 24.0]);
    assert_eq!(p.returns_to_go, vec![9.0; 5]);
}

/// A task of demonstrations with the given 2-d states (zero actions and rewards).
fn task_of_states(demos: &[&[[f32; 2]]]) -> TaskData {
    let trajs: Vec<Trajectory> = demos
        .iter()
        .map(|st| {
            let n = st.len();
            let obs = st.iter().flatten().copied().collect();
            Trajectory::new(2, 1, obs, vec![0.0; n], vec![0.0; n], vec![false; n], vec![false; n])
                .unwrap()
        })
        .collect();
    let ds = TaskDataset::new(trajs).unwrap();
    TaskData { id: TaskId { env: "toy".into(), index: 0 }, dataset: ds.clone(), prompts: ds }
}

#[test]
fn nearest_start_picks_the_segment_whose_first_state_is_nearest_in_normalised_space() {
    // From the start state (0, 0): demonstration 1's (0, 2) is nearer in raw space (2 < 3), but
    // with dimension 0 ten times wider (std 10) demonstration 0's (3, 0) is nearer (0.3 < 2).
    let t = task_of_states(&[&[[3.0, 0.0], [50.0, 50.0]], &[[0.0, 2.0], [50.0, 50.0]]]);
    let raw = sampler(&t, 1, 1, StateNorm::identity(2));
    let got = raw.nearest_start_segments(0, &[0.0, 0.0], 1).unwrap();
    assert_eq!(got, vec![SegmentChoice { demo: 1, start: 0 }]);
    let wide = StateNorm { mean: vec![5.0, -1.0], std: vec![10.0, 1.0] };
    let s = sampler(&t, 1, 1, wide);
    let got = s.nearest_start_segments(0, &[0.0, 0.0], 1).unwrap();
    assert_eq!(got, vec![SegmentChoice { demo: 0, start: 0 }]);
    // On the grid task (states (demo, step)): J = 2 takes the two nearest, nearest first.
    let g = task(&[1.0, 1.0, 1.0], 20);
    let s_id = sampler(&g, 2, 5, StateNorm::identity(2));
    let got = s_id.nearest_start_segments(0, &[0.0, 3.2], 1).unwrap();
    assert_eq!(got, vec![SegmentChoice { demo: 0, start: 3 }, SegmentChoice { demo: 0, start: 4 }]);
    // with stride 5 only starts 0, 5, 10, 15 are candidates
    let got = s_id.nearest_start_segments(0, &[2.0, 12.9], 5).unwrap();
    assert_eq!(got[0], SegmentChoice { demo: 2, start: 15 });
    // a start of 16 or later would not fit 5 steps in 20
    let got = s_id.nearest_start_segments(0, &[1.0, 19.0], 1).unwrap();
    assert_eq!(got[0], SegmentChoice { demo: 1, start: 15 });
    assert!(s_id.nearest_start_segments(0, &[0.0], 1).is_err());
}

#[test]
fn random_segment_is_reproducible_per_seed_and_differs_across_seeds() {
    let t = task(&[1.0, 2.0, 3.0, 4.0], 40);
    let s = sampler(&t, 2, 5, StateNorm::identity(2));
    let draw = |seed| s.random_segments(0, &mut Rng::seed_from_u64(seed));
    assert_eq!(draw(1), draw(1));
    assert_ne!(draw(1), draw(2));
    let mut starts = std::collections::BTreeSet::new();
    let mut r = Rng::seed_from_u64(5);
    for _ in 0..300 {
        for c in s.random_segments(0, &mut r) {
            assert!(c.demo < 4 && c.start <= 35, "{c:?}");
            starts.insert(c.start);
        }
    }
    assert!(starts.contains(&0) && starts.contains(&35) && starts.len() > 30);
}

#[test]
fn bandit_over_a_tasks_candidates_finds_the_segment_that_pays() {
    let t = task(&[1.0, 1.0], 20);
    let s = sampler(&t, 1, 5, StateNorm::identity(2));
    let arms = s.candidate_segments(0, 5); // starts 0, 5, 10, 15 of both demonstrations
    assert_eq!(arms.len(), 8);
    let target = SegmentChoice { demo: 1, start: 10 };
    let mut b = SegmentBandit::new(BanditConfig::default(), arms, 1).unwrap();
    let mut rng = Rng::seed_from_u64(0);
    let mut last = Vec::new();
    for round in 0..300 {
        let c = b.choose(&mut rng);
        let seg = b.segments(&c)[0];
        b.update(&c, &[if seg == target { 10.0 } else { 1.0 }]);
        if round >= 200 {
            last.push(seg);
        }
    }
    let hits = last.iter().filter(|&&c| c == target).count();
    assert!(hits > 80, "{hits} of 100");
}

#[test]
fn test_time_length_overrides_training_and_must_fit() {
    let trained = SamplerConfig::reference(1.0, 1000);
    let st = PromptStrategy { episodes: Some(2), length: Some(10), ..PromptStrategy::default() };
    let cfg = check_fits(&st, &trained, 1024).unwrap();
    assert_eq!((cfg.prompt_episodes, cfg.prompt_length, cfg.k), (2, 10, 20));
    let t = task(&[1.0], 30);
    let s = BatchSampler::new(cfg, &[&t], StateNorm::identity(2), 1024).unwrap();
    let p = s.eval_prompt(0, &mut Rng::seed_from_u64(0));
    assert_eq!(p.steps, 20);
    // J x H that overflows the model's positions is refused, naming the values
    let big = PromptStrategy { length: Some(400), ..PromptStrategy::default() };
    let e = check_fits(&big, &trained, 1024).unwrap_err().to_string();
    assert!(e.contains("1 x 400") && e.contains("1024"), "{e}");
    let zero = PromptStrategy { episodes: Some(0), ..PromptStrategy::default() };
    assert!(check_fits(&zero, &trained, 1024).unwrap_err().to_string().contains("episodes"));
}

#[test]
fn a_pick_with_a_nan_return_reads_back() {
    let p = pdt_prompt::PromptPick {
        task: "toy-0".into(),
        episode: 0,
        segments: vec![SegmentChoice { demo: 1, start: 2 }],
        round: Some(0),
        explored: Some(true),
        episode_return: f64::NAN,
    };
    let text = serde_json::to_string(&p).unwrap();
    assert!(text.contains("\"episode_return\":null"), "{text}");
    let back: pdt_prompt::PromptPick = serde_json::from_str(&text).unwrap();
    assert!(back.episode_return.is_nan() && back.segments == p.segments);
}
