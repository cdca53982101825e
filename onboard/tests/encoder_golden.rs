//! Pins the encoder's output bit for bit: trained models depend on every feature, so a change
//! to `obs::encode` that moves any feature by one ulp (a faster loop that reorders a sum, say)
//! must be a decision, with a new `ENCODER_VERSION` and new models, not an accident.

use skyherd_onboard::obs::{ENCODER_VERSION, FEATURES, ObsInput, V3_FEATURES, V4_FEATURES, encode};

/// xorshift64: the test's own seeded numbers.
struct Numbers(u64);

impl Numbers {
    fn unit(&mut self) -> f32 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 40) as f32 / (1u64 << 24) as f32
    }
}

/// FNV-1a over the bits of the first `width` features and of the frame, for a spread of
/// seeded worlds: N = 0..1024, M = 1..33, paper and room scale, and positions on a
/// quarter-metre grid so that distance ties (the ownership rule) occur.
fn fingerprint(width: usize) -> u64 {
    let mut hash = 0xcbf2_9ce4_8422_2325_u64;
    let mut eat = |bits: u32| {
        for byte in bits.to_le_bytes() {
            hash ^= u64::from(byte);
            hash = hash.wrapping_mul(0x0000_0100_0000_01b3);
        }
    };
    let mut numbers = Numbers(0x5EED_0FF1_E1D5);
    for case in 0..600usize {
        let n = [0usize, 1, 2, 3, 4, 7, 16, 33, 64, 255, 256, 1024][case % 12];
        let m = 1 + (case / 12) % 33;
        let scale = [10.0_f32, 500.0, 1.0][case % 3];
        let on_grid = case % 5 == 0;
        let point = |numbers: &mut Numbers| {
            let v = numbers.unit() * scale;
            if on_grid { (v * 4.0).round() / 4.0 } else { v }
        };
        let herders: Vec<[f32; 3]> = (0..m)
            .map(|_| {
                [
                    point(&mut numbers),
                    point(&mut numbers),
                    numbers.unit() * 3.0,
                ]
            })
            .collect();
        let mut targets: Vec<[f32; 2]> = (0..n)
            .map(|_| [point(&mut numbers), point(&mut numbers)])
            .collect();
        if case % 7 == 0 && n > 0 && m > 1 {
            // A target right under another herder.
            targets[0] = [herders[1][0], herders[1][1]];
        }
        let input = ObsInput {
            own_index: case % m,
            herders: &herders,
            targets: &targets,
            goal: [point(&mut numbers), point(&mut numbers)],
            goal_radius: 0.05 + numbers.unit() * scale * 0.1,
            area: [scale, scale, 3.0],
            max_speed: 1.0 + numbers.unit(),
        };
        let mut features = [0.0_f32; FEATURES];
        let frame = encode(&input, &mut features).expect("a valid observation");
        features[..width]
            .iter()
            .chain(&frame.forward)
            .for_each(|x| eat(x.to_bits()));
    }
    hash
}

#[test]
fn the_older_encoders_prefixes_are_pinned_bit_for_bit() {
    // Each computed with that encoder when its models were made, and checked equal for every
    // encoder since (each only appends): those models fly on exactly these numbers.
    for (version, width, pinned) in [
        // v3: mtddpg-v1 and -v2 (and the faster encoder that followed).
        (3, V3_FEATURES, 0xb2d6_da4c_c815_05ed_u64),
        // v4: mtddpg-v3 and the from-scratch models.
        (4, V4_FEATURES, 0x23f8_a442_1e34_fc58),
    ] {
        let got = fingerprint(width);
        assert_eq!(
            got, pinned,
            "the first {width} features changed ({got:#018x}): the v{version} models would fly on other numbers"
        );
    }
}

#[test]
fn the_encoder_output_is_pinned_bit_for_bit() {
    // Computed with encoder v5 when its assignment features were added.
    const PINNED: u64 = 0xb6ce_d42d_69bf_a7a2;
    assert_eq!(
        ENCODER_VERSION, 5,
        "a new encoder version needs a new pinned fingerprint"
    );
    let got = fingerprint(FEATURES);
    assert_eq!(
        got, PINNED,
        "the encoder's features changed ({got:#018x}); if on purpose, bump ENCODER_VERSION, retrain, and pin the new value"
    );
}
