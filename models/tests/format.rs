//! Model file round trip and every validation rule of `decode`.
#![cfg(feature = "std")]

use skyherd_model::format::{self, CRC32, FormatError, HEADER_LEN, LAYER_HEADER_LEN, MAX_WIDTH};
use skyherd_model::{ActorShape, FloatActor, ModelMeta, SplitMix64, Task, decode, quantize_model};

const SHAPE: ActorShape = ActorShape {
    features: 5,
    hidden: 7,
    shared_layers: 2,
};

fn model_bytes() -> Vec<u8> {
    let actor = FloatActor::random(SHAPE, 11);
    let mut rng = SplitMix64::new(3);
    let obs: Vec<(Task, Vec<f32>)> = (0..64)
        .map(|i| {
            let task = Task::ALL[i % 2];
            (
                task,
                (0..SHAPE.features)
                    .map(|_| rng.uniform(-2.0, 2.0) as f32)
                    .collect(),
            )
        })
        .collect();
    let meta = ModelMeta {
        encoder_version: 9,
        max_speed: 5.0,
    };
    quantize_model(&actor, meta, obs.iter().map(|(t, o)| (*t, &o[..])))
        .unwrap()
        .to_bytes()
}

/// Recomputes the CRC trailer after an edit, so the edit reaches the structural checks.
fn reseal(bytes: &mut [u8]) {
    let n = bytes.len() - 4;
    let crc = CRC32.checksum(&bytes[..n]);
    bytes[n..].copy_from_slice(&crc.to_le_bytes());
}

fn edited(offset: usize, value: &[u8]) -> Result<(), FormatError> {
    let mut bytes = model_bytes();
    bytes[offset..offset + value.len()].copy_from_slice(value);
    reseal(&mut bytes);
    decode(&bytes).map(|_| ())
}

#[test]
fn round_trip_exposes_every_field() {
    let bytes = model_bytes();
    assert_eq!(bytes.len(), format::file_len(5, 7, 2));
    let model = decode(&bytes).unwrap();
    assert_eq!(model.encoder_version, 9);
    assert_eq!(
        (model.features, model.hidden, model.shared_layers),
        (5, 7, 2)
    );
    assert_eq!(model.max_speed, 5.0);
    assert_eq!(model.layers().len(), 6);
    assert_eq!(model.shared().len(), 2);
    assert_eq!(model.task_input(Task::Collecting).inputs, 5);
    assert_eq!(model.task_output(Task::Collecting).outputs, 3);
    assert_eq!(model.weight_count(), 2 * 35 + 2 * 49 + 2 * 21);
    // The task input layers carry int16 weights, the others int8.
    assert_eq!(model.wide_weight_count(), 2 * 35);
    assert_eq!(
        model.task_input(Task::Driving).weight_width,
        format::WeightWidth::Int16
    );
    assert_eq!(model.shared()[0].weight_width, format::WeightWidth::Int8);
    assert!(model.task_input(Task::Driving).relu && !model.task_output(Task::Driving).relu);
    assert_eq!(model.check_encoder(9, 5), Ok(()));
    assert_eq!(
        model.check_encoder(1, 5),
        Err(FormatError::EncoderMismatch {
            model: (9, 5),
            expected: (1, 5)
        })
    );
}

#[test]
fn header_errors() {
    let bytes = model_bytes();
    assert!(matches!(decode(&[]), Err(FormatError::Truncated { .. })));
    assert_eq!(decode(b"SKYX\x01\x00").err(), Some(FormatError::BadMagic));
    // Format 1 (int8 activations) is not read any more.
    let mut b = bytes.clone();
    b[4] = 1;
    assert_eq!(decode(&b).err(), Some(FormatError::UnsupportedVersion(1)));
    let mut b = bytes.clone();
    b[6] = 31;
    assert_eq!(decode(&b).err(), Some(FormatError::BadHeaderLength(31)));
    assert!(matches!(
        decode(&bytes[..bytes.len() - 1]),
        Err(FormatError::LengthMismatch { .. })
    ));
    let mut b = bytes.clone();
    let last = b.len() - 1;
    b[last] ^= 1;
    assert!(matches!(decode(&b), Err(FormatError::CrcMismatch { .. })));
    let mut b = bytes.clone();
    b[40] ^= 0x10;
    assert!(matches!(decode(&b), Err(FormatError::CrcMismatch { .. })));
}

#[test]
fn structural_errors() {
    let too_wide = (MAX_WIDTH as u16 + 1).to_le_bytes();
    assert!(matches!(
        edited(14, &0u16.to_le_bytes()),
        Err(FormatError::Capacity { .. })
    ));
    assert!(matches!(
        edited(16, &too_wide),
        Err(FormatError::Capacity { .. })
    ));
    assert_eq!(edited(18, &[3]), Err(FormatError::TaskCount(3)));
    assert!(matches!(
        edited(19, &[9]),
        Err(FormatError::Capacity { .. })
    ));
    assert_eq!(edited(20, &[2]), Err(FormatError::ActionCount(2)));
    assert_eq!(edited(21, &[1]), Err(FormatError::ReservedNotZero(21)));
    assert_eq!(
        edited(28, &[0, 0, 0, 1]),
        Err(FormatError::ReservedNotZero(28))
    );
    assert_eq!(
        edited(24, &f32::NAN.to_le_bytes()),
        Err(FormatError::MaxSpeed)
    );
    assert_eq!(
        edited(24, &(-1.0f32).to_le_bytes()),
        Err(FormatError::MaxSpeed)
    );
    assert_eq!(
        edited(HEADER_LEN + 4, &0.0f32.to_le_bytes()),
        Err(FormatError::Scale {
            layer: None,
            channel: 1
        })
    );
    // First layer record starts after the 5 input scales (f32) and zero points (i16).
    let layer0 = HEADER_LEN + 6 * 5;
    assert_eq!(
        edited(layer0, &6u16.to_le_bytes()),
        Err(FormatError::LayerShape {
            layer: 0,
            expected: (5, 7),
            found: (6, 7)
        })
    );
    assert_eq!(
        edited(layer0 + 4, &[0]),
        Err(FormatError::Activation { layer: 0, code: 0 })
    );
    assert_eq!(
        edited(layer0 + 5, &[3]),
        Err(FormatError::WeightWidth { layer: 0, code: 3 })
    );
    // Int8 instead of int16: the record then ends early and the rest does not parse.
    assert!(edited(layer0 + 5, &[1]).is_err());
    assert_eq!(
        edited(layer0 + 8, &f32::INFINITY.to_le_bytes()),
        Err(FormatError::Scale {
            layer: Some(0),
            channel: 0
        })
    );
    // 35 int16 weights.
    let scales = layer0 + LAYER_HEADER_LEN + 2 * 35;
    assert_eq!(
        edited(scales + 4, &(-0.5f32).to_le_bytes()),
        Err(FormatError::Scale {
            layer: Some(0),
            channel: 1
        })
    );
    let bias = scales + 4 * 7;
    // An int16-weight layer's bias may reach 2^40, not beyond.
    assert_eq!(
        edited(bias, &((1i64 << 40) + 1).to_le_bytes()),
        Err(FormatError::Requantization {
            layer: 0,
            channel: 0
        })
    );
    assert!(edited(bias, &(1i64 << 40).to_le_bytes()).is_ok());
    let multiplier = bias + 8 * 7;
    assert_eq!(
        edited(multiplier + 8, &(-5i32).to_le_bytes()),
        Err(FormatError::Requantization {
            layer: 0,
            channel: 2
        })
    );
    let shift = multiplier + 4 * 7;
    assert_eq!(
        edited(shift + 6, &[0]),
        Err(FormatError::Requantization {
            layer: 0,
            channel: 6
        })
    );
    assert_eq!(
        edited(shift + 6, &[63]),
        Err(FormatError::Requantization {
            layer: 0,
            channel: 6
        })
    );
    // The shared layers have int8 weights: their bias must stay below 2^30.
    let layer2 = shift + 7 + format::layer_record_len(5, 7, format::INPUT_LAYER_WEIGHTS);
    let bias2 = layer2 + LAYER_HEADER_LEN + 49 + 4 * 7;
    assert_eq!(
        edited(bias2, &(1i64 << 30).to_le_bytes()),
        Err(FormatError::Requantization {
            layer: 2,
            channel: 0
        })
    );
    assert!(edited(bias2, &((1i64 << 30) - 1).to_le_bytes()).is_ok());
}

#[test]
fn trailing_and_missing_layer_bytes() {
    let bytes = model_bytes();
    let content = &bytes[..bytes.len() - 4];
    let seal = |content: &[u8]| {
        let mut b = content.to_vec();
        let len = (b.len() + 4) as u32;
        b[8..12].copy_from_slice(&len.to_le_bytes());
        b.extend_from_slice(&[0; 4]);
        reseal(&mut b);
        b
    };
    let mut longer = content.to_vec();
    longer.extend_from_slice(&[0, 0, 0]);
    assert_eq!(
        decode(&seal(&longer)).err(),
        Some(FormatError::TrailingBytes(3))
    );
    assert!(matches!(
        decode(&seal(&content[..content.len() - 2])),
        Err(FormatError::Truncated { .. })
    ));
}

#[test]
fn errors_display_as_sentences() {
    let e = FormatError::EncoderMismatch {
        model: (1, 46),
        expected: (2, 48),
    };
    assert_eq!(
        e.to_string(),
        "model was trained for observation encoder v1 (46 features), this build has v2 (48 features)"
    );
    assert!(FormatError::BadMagic.to_string().contains("magic"));
}
