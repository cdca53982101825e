//! `skyherd-model`: look inside and validate model files.
//!
//! ```text
//! skyherd-model inspect FILE...   header, layer shapes, sizes, CRC
//! skyherd-model validate FILE...  exit 0 when every file decodes, 1 otherwise
//! ```

use std::process::ExitCode;

use skyherd_model::{ModelView, Task, decode};

const USAGE: &str = "usage: skyherd-model <inspect|validate> FILE...";

fn describe(path: &str, model: &ModelView<'_>) {
    println!("{path}:");
    println!(
        "  file: {} bytes, CRC-32 {:#010x}",
        model.file_len(),
        model.crc()
    );
    println!(
        "  encoder: v{}, {} features; hidden {} x {} shared layers; max speed {} m/s",
        model.encoder_version, model.features, model.hidden, model.shared_layers, model.max_speed
    );
    println!(
        "  weights: {} ({} int16 in the task input layers, the rest int8)",
        model.weight_count(),
        model.wide_weight_count()
    );
    for (index, layer) in model.layers().iter().enumerate() {
        let role = if index < Task::COUNT {
            format!(
                "input[{:?}]",
                Task::from_index(index).unwrap_or(Task::Driving)
            )
        } else if index < Task::COUNT + model.shared_layers {
            format!("shared[{}]", index - Task::COUNT)
        } else {
            let t = index - Task::COUNT - model.shared_layers;
            format!("output[{:?}]", Task::from_index(t).unwrap_or(Task::Driving))
        };
        println!(
            "  layer {index:2} {role:<20} {:4} -> {:4} {:<5} {:<5} out scale {:.6} zp {}",
            layer.inputs,
            layer.outputs,
            if layer.relu { "relu" } else { "" },
            match layer.weight_width {
                skyherd_model::format::WeightWidth::Int8 => "int8",
                skyherd_model::format::WeightWidth::Int16 => "int16",
            },
            layer.output_scale,
            layer.output_zero_point
        );
    }
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let Some((command, files)) = args.split_first() else {
        eprintln!("{USAGE}");
        return ExitCode::from(2);
    };
    if !matches!(command.as_str(), "inspect" | "validate") || files.is_empty() {
        eprintln!("{USAGE}");
        return ExitCode::from(2);
    }
    let mut ok = true;
    for path in files {
        let bytes = match skyherd_model::read_model_file(std::path::Path::new(path)) {
            Ok(b) => b,
            Err(e) => {
                eprintln!("{path}: cannot read: {e}");
                ok = false;
                continue;
            }
        };
        match decode(&bytes) {
            Ok(model) if command == "inspect" => describe(path, &model),
            Ok(model) => println!(
                "{path}: ok ({} bytes, CRC-32 {:#010x}, encoder v{})",
                model.file_len(),
                model.crc(),
                model.encoder_version
            ),
            Err(e) => {
                eprintln!("{path}: invalid: {e}");
                ok = false;
            }
        }
    }
    if ok {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    }
}
