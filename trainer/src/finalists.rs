//! Finalists: the few best checkpoints of a run by the training-time check, and the end-of-run
//! choice among them on a second, independent episode set (`eval.finalists`).
//!
//! Why: the check herds one fixed set of episodes at some forty points of a run and keeps the
//! best, so the kept checkpoint's score reads high by the luck of that set (a 95 % actor scores
//! 100 % on the check now and then, and the fastest such actor wins). Re-scoring the top few on
//! episodes the check has never seen takes that luck out of the choice; it changes no learning.
//!
//! With `eval.average_finalists_from`, the mean of the late finalists' actors ([`mean_members`],
//! [`crate::network::MultiTaskMlp::mean_of`]) is one more candidate on the second set.
//!
//! The pure part (admission, the members of the mean, the CSV) is here; the I/O (saving, loading, herding) is in
//! [`crate::train`].
//!
//! ```
//! use skyherd_trainer::finalists::{Finalist, admit};
//! let mut kept = Vec::new();
//! for (steps, success, time) in [(100_000, 0.90, 3.0), (200_000, 1.0, 2.5), (300_000, 0.95, 2.0)] {
//!     admit(&mut kept, Finalist { env_steps: steps, check: (success, time) }, 2);
//! }
//! // Best first by success, then time; the weakest went.
//! assert_eq!(kept.iter().map(|f| f.env_steps).collect::<Vec<_>>(), [200_000, 300_000]);
//! ```

use std::path::{Path, PathBuf};

use crate::eval::better;

/// A checkpoint kept for the end-of-run choice.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Finalist {
    /// The run's env steps when it was checked (names its file).
    pub env_steps: u64,
    /// The training-time check's score: mean success, mean time over the lower bound.
    pub check: (f64, f64),
}

/// What [`admit`] did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Admission {
    /// The candidate is among the finalists now (its checkpoint is to be saved).
    pub kept: bool,
    /// The env steps of the finalist pushed out (its file is to be removed).
    pub dropped: Option<u64>,
}

/// Admits `candidate` to `finalists`, kept best first by the check's score ([`better`]) and at
/// most `capacity` long. An entry with the candidate's env steps (a resumed run checks a step
/// again) is replaced, so that step is always kept. A candidate that ties the last one is not
/// admitted: the earlier stays.
pub fn admit(finalists: &mut Vec<Finalist>, candidate: Finalist, capacity: usize) -> Admission {
    finalists.retain(|f| f.env_steps != candidate.env_steps);
    let at = finalists
        .iter()
        .position(|f| better(candidate.check, f.check))
        .unwrap_or(finalists.len());
    finalists.insert(at, candidate);
    let dropped = if finalists.len() > capacity {
        finalists.pop().map(|f| f.env_steps)
    } else {
        None
    };
    if dropped == Some(candidate.env_steps) {
        Admission {
            kept: false,
            dropped: None,
        }
    } else {
        Admission {
            kept: true,
            dropped,
        }
    }
}

/// The index of the best of `scores` by [`better`]; the first of equals wins (the finalists
/// come best first by the check, so the check breaks ties). `None` when empty.
pub fn choose(scores: &[(f64, f64)]) -> Option<usize> {
    (0..scores.len()).reduce(|best, i| {
        if better(scores[i], scores[best]) {
            i
        } else {
            best
        }
    })
}

/// The finalists averaged into one more candidate (`eval.average_finalists_from = from`):
/// those checked at or after `from` of the run's `run_env_steps`, in step order. Empty when
/// fewer than two qualify (one finalist is already a candidate of its own).
///
/// Why: late in a run the actor moves back and forth across a basin, and each checkpoint
/// carries that step's noise (one is fast at small flocks and drops targets at sixteen, the
/// next the other way); the mean of several sits nearer the basin's middle. Early finalists,
/// from before the actor had learned what the late ones know, are left out.
pub fn mean_members(finalists: &[Finalist], run_env_steps: u64, from: f64) -> Vec<u64> {
    let mut members: Vec<u64> = finalists
        .iter()
        .map(|f| f.env_steps)
        .filter(|&steps| steps as f64 >= from * run_env_steps as f64)
        .collect();
    members.sort_unstable();
    if members.len() < 2 {
        members.clear();
    }
    members
}

/// Where the mean of the finalists ([`mean_members`]) is saved: the latest member's checkpoint
/// with its actor replaced by the mean.
pub const MEAN_FILE: &str = "finalists-mean.safetensors";

/// The line of [`CSV_FILE`] for the mean of `members`, its final-set score and whether it was
/// chosen. Its first column names the members, so [`from_csv`] (which a resumed run reads)
/// skips it.
pub fn mean_csv_line(members: &[u64], score: (f64, f64), chosen: bool) -> String {
    let names: Vec<String> = members.iter().map(u64::to_string).collect();
    format!(
        "mean of {},,,{},{},{chosen}\n",
        names.join(" "),
        score.0,
        score.1
    )
}

/// Where finalist `env_steps` of the run in `dir` is saved.
pub fn file(dir: &Path, env_steps: u64) -> PathBuf {
    dir.join(format!("finalist-{env_steps}.safetensors"))
}

/// The record of a run's finalists, in its output folder.
pub const CSV_FILE: &str = "finalists.csv";

/// The columns of [`CSV_FILE`]: the final columns are empty until the end-of-run choice.
pub const CSV_HEADER: &str =
    "env_steps,check_success,check_time_ratio,final_success,final_time_ratio,chosen";

/// The CSV of `finalists`, with each one's final-set score and whether it was chosen where
/// given (`finals[i]` belongs to `finalists[i]`).
pub fn to_csv(finalists: &[Finalist], finals: Option<(&[(f64, f64)], usize)>) -> String {
    let mut s = String::from(CSV_HEADER);
    s.push('\n');
    for (i, f) in finalists.iter().enumerate() {
        s.push_str(&format!("{},{},{}", f.env_steps, f.check.0, f.check.1));
        match finals {
            Some((scores, chosen)) if i < scores.len() => {
                s.push_str(&format!(
                    ",{},{},{}\n",
                    scores[i].0,
                    scores[i].1,
                    i == chosen
                ));
            }
            _ => s.push_str(",,,\n"),
        }
    }
    s
}

/// The finalists in a CSV written by [`to_csv`]; a line that does not read (a torn write) is
/// skipped, as is the header.
pub fn from_csv(text: &str) -> Vec<Finalist> {
    text.lines()
        .skip(1)
        .filter_map(|line| {
            let mut cols = line.split(',');
            let env_steps = cols.next()?.parse().ok()?;
            let success = cols.next()?.parse().ok()?;
            let time = cols.next()?.parse().ok()?;
            Some(Finalist {
                env_steps,
                check: (success, time),
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn f(env_steps: u64, success: f64, time: f64) -> Finalist {
        Finalist {
            env_steps,
            check: (success, time),
        }
    }

    fn steps(list: &[Finalist]) -> Vec<u64> {
        list.iter().map(|f| f.env_steps).collect()
    }

    #[test]
    fn the_weakest_goes_once_the_list_is_full() {
        let mut list = Vec::new();
        assert_eq!(
            admit(&mut list, f(1, 0.5, 5.0), 2),
            Admission {
                kept: true,
                dropped: None
            }
        );
        assert_eq!(
            admit(&mut list, f(2, 0.9, 4.0), 2),
            Admission {
                kept: true,
                dropped: None
            }
        );
        // Same success, faster: it goes in ahead of the other 0.9 and pushes 0.5 out.
        assert_eq!(
            admit(&mut list, f(3, 0.9, 3.0), 2),
            Admission {
                kept: true,
                dropped: Some(1)
            }
        );
        assert_eq!(steps(&list), [3, 2]);
        // Worse than both: not kept, nothing of the list's goes.
        assert_eq!(
            admit(&mut list, f(4, 0.8, 1.0), 2),
            Admission {
                kept: false,
                dropped: None
            }
        );
        // A tie with the last does not push it out.
        assert_eq!(
            admit(&mut list, f(5, 0.9, 4.0), 2),
            Admission {
                kept: false,
                dropped: None
            }
        );
        assert_eq!(steps(&list), [3, 2]);
    }

    #[test]
    fn a_step_checked_again_replaces_its_entry() {
        let mut list = vec![f(3, 0.9, 3.0), f(2, 0.9, 4.0)];
        // Checked again, now the best: one entry for step 2, nothing dropped.
        assert_eq!(
            admit(&mut list, f(2, 1.0, 2.0), 2),
            Admission {
                kept: true,
                dropped: None
            }
        );
        assert_eq!(steps(&list), [2, 3]);
        // Checked again and now the worst: it stays (its old slot is free), last.
        assert_eq!(
            admit(&mut list, f(2, 0.1, 9.0), 2),
            Admission {
                kept: true,
                dropped: None
            }
        );
        assert_eq!(steps(&list), [3, 2]);
        assert_eq!(list[1].check, (0.1, 9.0));
    }

    #[test]
    fn the_choice_is_by_the_final_score_and_the_check_breaks_ties() {
        assert_eq!(choose(&[]), None);
        assert_eq!(choose(&[(0.97, 2.0), (0.99, 2.5), (0.95, 1.5)]), Some(1));
        assert_eq!(choose(&[(0.99, 2.5), (0.99, 2.5)]), Some(0));
        // Within half an episode in a hundred, time decides.
        assert_eq!(choose(&[(0.99, 2.5), (0.987, 2.2)]), Some(1));
    }

    #[test]
    fn the_mean_takes_the_late_finalists_and_only_when_there_are_two() {
        let list = vec![
            f(900_000, 1.0, 2.0),
            f(250_000, 1.0, 3.0),
            f(650_000, 0.99, 2.1),
            f(500_000, 0.99, 2.2),
        ];
        assert_eq!(
            mean_members(&list, 1_000_000, 0.5),
            [500_000, 650_000, 900_000]
        );
        assert_eq!(mean_members(&list, 1_000_000, 0.0).len(), 4);
        // One late finalist is no mean.
        assert!(mean_members(&list, 1_000_000, 0.8).is_empty());
        assert!(mean_members(&[], 1_000_000, 0.5).is_empty());
        // The mean's line does not read back as a finalist.
        let mut text = to_csv(&list, None);
        text.push_str(&mean_csv_line(&[650_000, 900_000], (0.99, 1.9), true));
        assert!(text.ends_with("mean of 650000 900000,,,0.99,1.9,true\n"));
        assert_eq!(from_csv(&text), list);
    }

    #[test]
    fn the_csv_reads_back_and_skips_torn_lines() {
        let list = vec![f(300_000, 1.0, 2.03), f(500_000, 0.993, 1.9)];
        let text = to_csv(&list, None);
        assert_eq!(
            text,
            "env_steps,check_success,check_time_ratio,final_success,final_time_ratio,chosen\n\
             300000,1,2.03,,,\n500000,0.993,1.9,,,\n"
        );
        assert_eq!(from_csv(&text), list);
        let done = to_csv(&list, Some((&[(0.97, 2.1), (0.99, 2.0)], 1)));
        assert!(done.ends_with("300000,1,2.03,0.97,2.1,false\n500000,0.993,1.9,0.99,2,true\n"));
        assert_eq!(from_csv(&done), list);
        assert_eq!(from_csv(&format!("{text}70000,0.5")), list);
    }
}
