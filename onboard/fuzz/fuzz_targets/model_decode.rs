//! Model file decoder: any bytes either fail with an error or decode into a model that the
//! quantized actor runs without panicking.
#![no_main]

use libfuzzer_sys::fuzz_target;
use skyherd_model::{Task, decode};
use skyherd_onboard::actor::infer_quantized_any;

fuzz_target!(|data: &[u8]| {
    if let Ok(model) = decode(data) {
        for task in Task::ALL {
            let _ = infer_quantized_any(&model, task, &[0.5; 64]);
        }
    }
});
