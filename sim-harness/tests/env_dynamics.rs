//! The simulator's herders through the multicopter model (`Scenario::dynamics`): off, every
//! episode is what it was; on, a herder lags its command and the wind pushes it, reproducibly.

use skyherd_sim::dynamics::{DynamicsLimits, WindConfig};
use skyherd_sim::scenario::HerderDynamics;
use skyherd_sim::{Env, HerderCount, Scenario};

fn scenario(dynamics: Option<HerderDynamics>) -> Scenario {
    let mut s = Scenario::paper_drive();
    s.targets = 4;
    s.herders = HerderCount::Fixed(2);
    s.dynamics = dynamics;
    s
}

/// Every herder commanded `command` (m/s) for `steps` steps; the herders' positions after each.
fn fly(s: &Scenario, seed: u64, command: [f64; 3], steps: usize) -> Vec<Vec<[f64; 3]>> {
    let mut env = Env::new(s.clone()).expect("valid scenario");
    env.reset(seed);
    let m = env.world().herders.len();
    (0..steps)
        .map(|_| {
            env.step(&vec![command; m]).expect("steps");
            env.world().herders.clone()
        })
        .collect()
}

#[test]
fn without_dynamics_a_herder_flies_its_command_at_once() {
    let mut s = scenario(None);
    s.noise.actuation_std = 0.0;
    let start = {
        let mut env = Env::new(s.clone()).unwrap();
        env.reset(3);
        env.world().herders.clone()
    };
    let after = fly(&s, 3, [5.0, 0.0, 0.0], 1);
    for (a, b) in start.iter().zip(&after[0]) {
        assert!((b[0] - a[0] - 5.0).abs() < 1e-9, "{a:?} -> {b:?}");
    }
}

#[test]
fn with_px4_dynamics_a_herder_lags_then_catches_up() {
    let mut s = scenario(Some(HerderDynamics {
        limits: DynamicsLimits::px4(),
        wind: WindConfig::CALM,
        command_delay_s: 0.0,
    }));
    s.noise.actuation_std = 0.0;
    let start = {
        let mut env = Env::new(s.clone()).unwrap();
        env.reset(3);
        env.world().herders.clone()
    };
    let path = fly(&s, 3, [5.0, 0.0, 0.0], 6);
    let first = path[0][0][0] - start[0][0];
    // Offboard, through the velocity loop's 0.55 s lag from a hover: about
    // 5 (1 - 0.55 (1 - e^(-1/0.55))) = 2.7 m in the first second, not 5.
    assert!(first > 2.2 && first < 3.2, "first step {first} m");
    // By the sixth second it flies the full 5 m/s.
    let last = path[5][0][0] - path[4][0][0];
    assert!((last - 5.0).abs() < 0.1, "sixth step {last} m");
    // PX4's jerk-limited mission trajectory is slower still off the mark.
    let mut smoothed = s.clone();
    if let Some(d) = smoothed.dynamics.as_mut() {
        d.limits = DynamicsLimits::px4_auto();
    }
    let path = fly(&smoothed, 3, [5.0, 0.0, 0.0], 6);
    let first_auto = path[0][0][0] - start[0][0];
    assert!(
        first_auto > 0.0 && first_auto < 2.0,
        "first step {first_auto} m"
    );
}

#[test]
fn a_delayed_command_is_flown_from_its_arrival() {
    let mut s = scenario(Some(HerderDynamics {
        limits: DynamicsLimits::px4(),
        wind: WindConfig::CALM,
        command_delay_s: 1.0,
    }));
    s.noise.actuation_std = 0.0;
    let start = {
        let mut env = Env::new(s.clone()).unwrap();
        env.reset(3);
        env.world().herders.clone()
    };
    // A whole step late (the paper's 1 s step): the first step still hovers, the second flies
    // what the first asked for, as the undelayed drone flew it in its first step.
    let late = fly(&s, 3, [5.0, 0.0, 0.0], 2);
    assert!(
        (late[0][0][0] - start[0][0]).abs() < 1e-9,
        "{:?}",
        late[0][0]
    );
    let mut prompt = s.clone();
    if let Some(d) = prompt.dynamics.as_mut() {
        d.command_delay_s = 0.0;
    }
    let on_time = fly(&prompt, 3, [5.0, 0.0, 0.0], 1);
    let a = late[1][0][0] - late[0][0][0];
    let b = on_time[0][0][0] - start[0][0];
    assert!((a - b).abs() < 1e-9, "{a} vs {b}");
    // More than a step is refused, by name.
    if let Some(d) = s.dynamics.as_mut() {
        d.command_delay_s = 1.5;
    }
    let err = s.validate().unwrap_err().to_string();
    assert!(err.contains("dynamics.command_delay_s"), "{err}");
}

#[test]
fn the_wind_pushes_reproducibly() {
    let s = scenario(Some(HerderDynamics {
        limits: DynamicsLimits::px4(),
        wind: WindConfig::arena(),
        command_delay_s: 0.0,
    }));
    let a = fly(&s, 11, [0.0; 3], 20);
    let b = fly(&s, 11, [0.0; 3], 20);
    assert_eq!(a, b, "same seed, same gusts");
    let c = fly(&s, 12, [0.0; 3], 20);
    assert_ne!(a, c, "another seed, other gusts");
    // Commanded to hover, the herders drift in the 3 m/s mean wind.
    let start = {
        let mut env = Env::new(s.clone()).unwrap();
        env.reset(11);
        env.world().herders.clone()
    };
    let drift: f64 = a[19]
        .iter()
        .zip(&start)
        .map(|(p, q)| ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2)).sqrt())
        .sum();
    assert!(drift > 0.5, "drift {drift} m");
}

#[test]
fn dynamics_round_trip_through_toml_and_bad_values_are_refused() {
    let s = scenario(Some(HerderDynamics {
        limits: DynamicsLimits::indoor(),
        wind: WindConfig::room(),
        command_delay_s: 0.0,
    }));
    let text = s.to_toml().expect("serializes");
    assert!(text.contains("[dynamics.limits]"), "{text}");
    assert_eq!(Scenario::from_toml_str(&text).expect("parses"), s);
    // A preset has none, and says nothing of it.
    assert!(
        !Scenario::paper_drive()
            .to_toml()
            .unwrap()
            .contains("dynamics")
    );
    let mut bad = s.clone();
    if let Some(d) = bad.dynamics.as_mut() {
        d.limits.max_jerk = f64::NAN;
    }
    let err = bad.validate().unwrap_err().to_string();
    assert!(
        err.contains("dynamics.limits") && err.contains("max_jerk"),
        "{err}"
    );
}
