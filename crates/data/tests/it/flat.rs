//! Flat step arrays with a task column cut back into per-task datasets (`pdt_data::flat`), every
//! bad array refused naming the file, the array and the step; prompt sets by the named rule.

use pdt_data::flat::{FlatSteps, PromptRule};
use std::path::Path;

/// 3 episodes: two of task 1 (lengths 2 and 3), one of task 0 (length 1); obs 2, act 1.
fn flat() -> FlatSteps {
    FlatSteps {
        obs_dim: 2,
        act_dim: 1,
        observations: (0..12).map(|x| x as f32).collect(),
        actions: vec![0.1, 0.2, 0.3, 0.4, 0.5, 0.6],
        rewards: vec![1.0, 1.0, 5.0, 5.0, 5.0, 2.0],
        terminals: vec![false, true, false, false, false, false],
        timeouts: vec![false, false, false, false, true, true],
        task_ids: vec![1, 1, 1, 1, 1, 0],
    }
}

fn error(f: &FlatSteps) -> String {
    let e = f.split_by_task(Path::new("my.npz"), 2).expect_err("refused").to_string();
    assert!(e.contains("my.npz"), "{e}");
    e
}

#[test]
fn steps_are_cut_into_episodes_per_task() {
    let tasks = flat().split_by_task(Path::new("my.npz"), 2).unwrap();
    assert_eq!(tasks.keys().copied().collect::<Vec<_>>(), vec![0, 1]);
    let t1 = &tasks[&1];
    assert_eq!(t1.trajectories.len(), 2);
    assert_eq!(t1.trajectories[0].len(), 2);
    assert_eq!(t1.trajectories[0].terminated, vec![false, true]);
    assert_eq!(t1.trajectories[1].truncated, vec![false, false, true]);
    assert_eq!(t1.trajectories[1].observations, vec![4.0, 5.0, 6.0, 7.0, 8.0, 9.0]);
    assert_eq!(tasks[&0].trajectories[0].actions, vec![0.6]);
    // Best return first: the 15-return episode, then the 2-return one.
    let p = PromptRule::BestReturn { episodes: 1 }.prompts(t1);
    assert_eq!(p.trajectories, vec![t1.trajectories[1].clone()]);
    assert_eq!(PromptRule::BestReturn { episodes: 9 }.prompts(t1).trajectories.len(), 2);
    assert_eq!("best:3".parse(), Ok(PromptRule::BestReturn { episodes: 3 }));
    assert!("best:0".parse::<PromptRule>().is_err() && "top".parse::<PromptRule>().is_err());
}

#[test]
fn bad_arrays_are_refused_naming_the_array_and_step() {
    let mut f = flat();
    f.actions.pop();
    assert!(error(&f).contains("`actions` has 5 values"));
    let mut f = flat();
    f.observations[7] = f32::NAN;
    assert!(error(&f).contains("`observations` at step 3 is NaN"));
    let mut f = flat();
    f.task_ids[2] = 2;
    let e = error(&f);
    assert!(e.contains("`task_ids` at step 2 is 2; the suite has tasks 0..2"), "{e}");
    let mut f = flat();
    f.task_ids[3] = 0;
    let e = error(&f);
    assert!(e.contains("changes from 1 to 0 at step 3"), "{e}");
    let mut f = flat();
    f.timeouts[5] = false;
    assert!(error(&f).contains("the last step (5) ends no episode"));
    let mut f = flat();
    f.rewards.clear();
    assert!(error(&f).contains("no steps"));
}
