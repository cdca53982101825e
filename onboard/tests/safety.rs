//! Safety rules, exhaustively over stale x non-finite x outside-fence x over-speed, and the
//! invariants every decision must keep.

use skyherd_onboard::safety::{Decision, Limits, Reasons, Situation, check};

const AREA: [f32; 3] = [500.0, 500.0, 10.0];

fn limits() -> Limits {
    Limits::arena(AREA, 5.0)
}

fn inside(p: [f32; 3], l: &Limits) -> bool {
    (0..3).all(|i| (l.fence_min[i]..=l.fence_max[i]).contains(&p[i]))
}

/// The invariants: finite, within the speed limits, never outward when outside a bound, never
/// leaving within the look-ahead when inside.
fn assert_safe(s: &Situation, d: &Decision, l: &Limits) {
    assert!(d.velocity.iter().all(|v| v.is_finite()), "{s:?} -> {d:?}");
    assert!(d.speed() <= l.max_speed * 1.0001, "{s:?} -> {d:?}");
    assert!(
        d.velocity[2].abs() <= l.max_vertical_speed * 1.0001,
        "{s:?} -> {d:?}"
    );
    if !s.position.iter().all(|x| x.is_finite()) {
        assert_eq!(d.velocity, [0.0; 3]);
        return;
    }
    for i in 0..3 {
        let (p, v) = (s.position[i], d.velocity[i]);
        if p < l.fence_min[i] {
            assert!(v > 0.0, "axis {i} below fence must move in: {s:?} -> {d:?}");
        } else if p > l.fence_max[i] {
            assert!(v < 0.0, "axis {i} above fence must move in: {s:?} -> {d:?}");
        } else {
            let next = p + v * l.lookahead_s;
            assert!(
                next >= l.fence_min[i] - 1e-3 && next <= l.fence_max[i] + 1e-3,
                "axis {i} would leave: {s:?} -> {d:?}"
            );
        }
    }
}

#[test]
fn exhaustive_over_stale_nonfinite_outside_overspeed() {
    let l = limits();
    let stale_ages = [
        (false, 0.2),
        (true, 1.5),
        (true, f32::NAN),
        (true, -0.1),
        (true, f32::INFINITY),
    ];
    // Where the non-finite value sits: nowhere, the snapshot, the position, the velocity.
    let non_finite = [None, Some(0), Some(1), Some(2)];
    let positions = [
        (false, [250.0, 250.0, 5.0]),
        (true, [-20.0, 250.0, 5.0]),
        (true, [250.0, 600.0, 5.0]),
        (true, [250.0, 250.0, 0.1]),
        (true, [250.0, 250.0, 12.0]),
        (true, [-5.0, 505.0, 11.0]),
    ];
    let velocities = [
        (false, [1.0, -2.0, 0.5]),
        (true, [30.0, 0.0, 0.0]),
        (true, [0.0, 0.0, -4.0]),
        (true, [-8.0, 8.0, 3.0]),
    ];
    let mut cases = 0;
    for &(stale, age) in &stale_ages {
        for &nan_at in &non_finite {
            for &(outside, position) in &positions {
                for &(fast, velocity) in &velocities {
                    for bad in [f32::NAN, f32::INFINITY] {
                        let mut s = Situation {
                            position,
                            velocity,
                            snapshot_age_s: age,
                            snapshot_finite: nan_at != Some(0),
                            current_velocity: None,
                        };
                        match nan_at {
                            Some(1) => s.position[1] = bad,
                            Some(2) => s.velocity[0] = bad,
                            _ => {}
                        }
                        let d = check(&l, &s);
                        cases += 1;
                        assert_safe(&s, &d, &l);
                        let hold = stale || nan_at.is_some();
                        assert_eq!(d.hold, hold, "{s:?} -> {d:?}");
                        assert_eq!(d.reasons.contains(Reasons::STALE), stale);
                        assert_eq!(d.reasons.contains(Reasons::NON_FINITE), nan_at.is_some());
                        let position_known = nan_at != Some(1);
                        if outside && position_known {
                            assert!(
                                d.reasons.contains(Reasons::OUTSIDE_FENCE)
                                    || d.reasons.contains(Reasons::ALTITUDE),
                                "{s:?} -> {d:?}"
                            );
                        }
                        if !hold && !outside && fast {
                            assert!(d.reasons.contains(Reasons::OVER_SPEED), "{s:?} -> {d:?}");
                        }
                        if hold && !outside {
                            assert_eq!(d.velocity, [0.0; 3], "hold inside means zero velocity");
                        }
                        if !hold && !outside && !fast {
                            assert_eq!(d.velocity, velocity, "a safe request passes unchanged");
                            assert!(d.reasons.is_empty());
                        }
                    }
                }
            }
        }
    }
    assert_eq!(cases, 5 * 4 * 6 * 4 * 2);
}

#[test]
fn near_fence_requests_are_trimmed_not_reversed() {
    let l = limits();
    let s = Situation {
        position: [498.5, 250.0, 5.0],
        velocity: [4.0, 0.0, 0.0],
        snapshot_age_s: 0.0,
        snapshot_finite: true,
        current_velocity: None,
    };
    let d = check(&l, &s);
    assert!(d.reasons.contains(Reasons::FENCE_LIMITED) && !d.hold);
    assert!((d.velocity[0] - 0.5).abs() < 1e-5, "{d:?}");
    assert!(inside([s.position[0] + d.velocity[0], 250.0, 5.0], &l));
    // Moving away from the fence is untouched.
    let away = check(
        &l,
        &Situation {
            velocity: [-4.0, 0.0, 0.0],
            ..s
        },
    );
    assert_eq!(away.velocity, [-4.0, 0.0, 0.0]);
}

#[test]
fn invalid_limits_hold() {
    for broken in [
        Limits {
            max_speed: f32::NAN,
            ..limits()
        },
        Limits {
            max_speed: 0.0,
            ..limits()
        },
        Limits {
            fence_min: [10.0, 0.0, 0.0],
            fence_max: [5.0, 10.0, 10.0],
            ..limits()
        },
        Limits {
            lookahead_s: -1.0,
            ..limits()
        },
    ] {
        let s = Situation {
            position: [1.0, 1.0, 1.0],
            velocity: [1.0, 0.0, 0.0],
            snapshot_age_s: 0.0,
            snapshot_finite: true,
            current_velocity: None,
        };
        let d = check(&broken, &s);
        assert!(d.hold && d.reasons == Reasons::INVALID_LIMITS && d.velocity == [0.0; 3]);
    }
}

#[test]
fn reasons_display() {
    assert_eq!(Reasons::NONE.to_string(), "ok");
    assert_eq!(
        (Reasons::STALE | Reasons::OVER_SPEED).to_string(),
        "stale snapshot, over speed"
    );
}

#[test]
fn the_fence_margin_shrinks_in_a_small_room() {
    assert_eq!(Limits::fence_margin([500.0, 500.0, 10.0]), 1.0);
    assert_eq!(Limits::fence_margin([10.0, 12.0, 3.0]), 0.25);
    let room = Limits::arena([10.0, 10.0, 3.0], 1.0);
    assert_eq!(room.fence_min, [0.25, 0.25, 0.5]);
    assert_eq!(room.fence_max, [9.75, 9.75, 2.5]);
    assert!(room.is_valid());
    // A nonsense area gives no margin, and limits that report themselves unusable.
    assert_eq!(Limits::fence_margin([f32::NAN, f32::NAN, 3.0]), 0.0);
    assert_eq!(Limits::fence_margin([-5.0, 10.0, 3.0]), 0.0);
    assert!(!Limits::arena([f32::NAN, 10.0, 3.0], 1.0).is_valid());
}

#[test]
fn braking_keeps_the_stopping_distance_to_the_fence() {
    use skyherd_onboard::safety::Braking;
    let braking = Braking {
        deceleration: 0.5,
        lag_s: 0.6,
    };
    // v * lag + v^2 / (2 a) = d: from 1 m/s it needs 0.6 + 1.0 = 1.6 m.
    assert!((braking.stopping_speed(1.6) - 1.0).abs() < 1e-5);
    assert_eq!(braking.stopping_speed(0.0), 0.0);
    assert_eq!(braking.stopping_speed(-1.0), 0.0);
    let room = Limits::arena([10.0, 10.0, 3.0], 1.0);
    let braked = Limits {
        braking: Some(braking),
        ..room
    };
    // 1 m short of the east fence (at 9.75 m), asked east at 1 m/s.
    let s = Situation {
        position: [8.75, 5.0, 1.0],
        velocity: [1.0, 0.0, 0.0],
        snapshot_age_s: 0.0,
        snapshot_finite: true,
        current_velocity: None,
    };
    // Without braking the look-ahead lets 1 m/s through; with it, only what stops in 1 m.
    assert_eq!(check(&room, &s).velocity[0], 1.0);
    let d = check(&braked, &s);
    assert!(
        (d.velocity[0] - braking.stopping_speed(1.0)).abs() < 1e-6,
        "{d:?}"
    );
    assert!(d.velocity[0] < 0.75 && d.reasons.contains(Reasons::FENCE_LIMITED));
    // Already flying east at 1 m/s, 1 m short: too fast to stop there, so it stops now.
    let fast = Situation {
        current_velocity: Some([1.0, 0.0, 0.0]),
        ..s
    };
    let d = check(&braked, &fast);
    assert_eq!(d.velocity[0], 0.0, "{d:?}");
    // Slow enough: the stopping speed, as without a known velocity.
    let slow = Situation {
        current_velocity: Some([0.5, 0.0, 0.0]),
        ..s
    };
    assert!((check(&braked, &slow).velocity[0] - braking.stopping_speed(1.0)).abs() < 1e-6);
    // Away from the fence nothing changes, and bad braking values are invalid limits.
    let away = Situation {
        velocity: [-1.0, 0.0, 0.0],
        ..s
    };
    assert_eq!(check(&braked, &away).velocity, [-1.0, 0.0, 0.0]);
    for bad in [
        Braking {
            deceleration: 0.0,
            lag_s: 0.1,
        },
        Braking {
            deceleration: f32::NAN,
            lag_s: 0.1,
        },
        Braking {
            deceleration: 1.0,
            lag_s: -0.1,
        },
    ] {
        assert!(
            !Limits {
                braking: Some(bad),
                ..room
            }
            .is_valid()
        );
    }
}
