//! Checkpoints as safetensors: every network of the [`Agent`] (actor, critic, both targets), the
//! Adam moments, and in the metadata the training progress and the run's config, so a run can
//! `--resume` where it stopped.
//!
//! Tensor names: `{net}.{part}.{index}.{weight|bias}` with `net` one of `actor`, `critic`,
//! `target_actor`, `target_critic`, `actor_adam_m`, `actor_adam_v`, `critic_adam_m`,
//! `critic_adam_v` (with twin critics also `critic2`, `target_critic2`, `critic2_adam_m`,
//! `critic2_adam_v`; with the advantage-decomposed critic `value`, `target_value`,
//! `value_adam_m`, `value_adam_v` and with twins the same with `value2`), and `part` one of
//! `task_inputs`, `shared`, `task_outputs`. Weights are
//! `[outputs, inputs]` row-major f32, as in `skyherd_model::Dense`.
//!
//! The replay buffers are not saved (hundreds of MB); a resumed run refills them.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::config::TrainConfig;
use crate::ddpg::{Agent, StateValue, TwinCritic};
use crate::network::MultiTaskMlp;
use crate::nn::{Activation, Adam, AdamConfig, Dense};

/// Why a checkpoint could not be written or read.
#[derive(Debug, Error)]
pub enum CheckpointError {
    /// File system trouble.
    #[error("checkpoint {path}: {source}")]
    Io {
        /// The path.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// The safetensors container is malformed.
    #[error("checkpoint format: {0}")]
    Format(String),
    /// A tensor is missing or has the wrong shape.
    #[error("checkpoint tensor `{0}` missing or malformed")]
    Tensor(String),
    /// The metadata is missing a key or holds a bad value.
    #[error("checkpoint metadata `{0}` missing or malformed")]
    Metadata(&'static str),
}

/// Where a run stands; saved beside the weights.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Progress {
    /// DDPG environment steps done.
    pub env_steps: u64,
    /// Finished training episodes.
    pub episodes: u64,
    /// Whether the warm start is behind us.
    pub warm_start_done: bool,
    /// Wall-clock seconds spent so far (over all sessions of the run).
    pub wall_time_s: f64,
    /// Best evaluation so far: success rate.
    pub best_success: f64,
    /// Best evaluation so far: mean time of successful episodes over the lower bound.
    pub best_time_ratio: f64,
    /// Stalled-task resets done, per task (`Task::index`); older checkpoints read as none.
    #[serde(default)]
    pub task_resets: [u32; 2],
    /// Env steps of the DDPG phase at each task's last reset (0: never reset): where its
    /// curriculum and its patience count from.
    #[serde(default)]
    pub task_reset_env_steps: [u64; 2],
    /// Each task's best mean held-out success since its last reset.
    #[serde(default)]
    pub task_best_since_reset: [f64; 2],
    /// Env steps of the DDPG phase at each task's last evaluation that reached
    /// `training.task_reset_below` (0: none yet); the `recent` reset rule's patience counts
    /// from here. Older checkpoints read as none.
    #[serde(default)]
    pub task_last_pass_env_steps: [u64; 2],
    /// Each task's mean held-out success at its latest evaluation (0 before the first, and
    /// after a reset): what `training.passed_task_update_share` reads. Older checkpoints read
    /// as none.
    #[serde(default)]
    pub task_latest_success: [f64; 2],
    /// Env steps of the DDPG phase each task has had (`Task::index`). Older checkpoints read
    /// as none, and a resumed run shares their `env_steps` evenly between its tasks, as their
    /// environments did.
    #[serde(default)]
    pub task_env_steps: [u64; 2],
}

/// Everything a checkpoint holds.
#[derive(Clone, Debug)]
pub struct Checkpoint {
    /// The networks and optimisers.
    pub agent: Agent,
    /// Counters.
    pub progress: Progress,
    /// The run's config.
    pub config: TrainConfig,
}

const NETS: [&str; 4] = ["actor", "critic", "target_actor", "target_critic"];

/// The state values of an advantage-decomposed critic: the network, its target, its Adam
/// moments and the metadata key of its Adam step, for the first and the twin's.
const VALUE_NETS: [[&str; 5]; 2] = [
    [
        "value",
        "target_value",
        "value_adam_m",
        "value_adam_v",
        "value_adam_step",
    ],
    [
        "value2",
        "target_value2",
        "value2_adam_m",
        "value2_adam_v",
        "value2_adam_step",
    ],
];

fn layer_groups(net: &MultiTaskMlp) -> [(&'static str, &[Dense]); 3] {
    [
        ("task_inputs", &net.task_inputs),
        ("shared", &net.shared),
        ("task_outputs", &net.task_outputs),
    ]
}

fn f32_bytes(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// Writes `(name, shape, bytes)` for every tensor of `net` under `prefix`.
fn push_net(out: &mut Vec<(String, Vec<usize>, Vec<u8>)>, prefix: &str, net: &MultiTaskMlp) {
    for (part, layers) in layer_groups(net) {
        for (i, l) in layers.iter().enumerate() {
            out.push((
                format!("{prefix}.{part}.{i}.weight"),
                vec![l.outputs, l.inputs],
                f32_bytes(&l.weights),
            ));
            out.push((
                format!("{prefix}.{part}.{i}.bias"),
                vec![l.outputs],
                f32_bytes(&l.bias),
            ));
        }
    }
}

/// The networks of an Adam state, in the network's layer order, as a [`MultiTaskMlp`] shape.
fn adam_as_net(adam: &[Dense], like: &MultiTaskMlp) -> MultiTaskMlp {
    let mut net = like.zeros_like();
    for (dst, src) in net.layers_mut().zip(adam) {
        dst.clone_from(src);
    }
    net
}

/// Serialises a checkpoint to safetensors bytes.
pub fn to_bytes(checkpoint: &Checkpoint) -> Result<Vec<u8>, CheckpointError> {
    let a = &checkpoint.agent;
    let mut tensors = Vec::new();
    for (name, net) in NETS
        .iter()
        .zip([&a.actor, &a.critic, &a.target_actor, &a.target_critic])
    {
        push_net(&mut tensors, name, net);
    }
    push_net(
        &mut tensors,
        "actor_adam_m",
        &adam_as_net(&a.actor_optimizer.first, &a.actor),
    );
    push_net(
        &mut tensors,
        "actor_adam_v",
        &adam_as_net(&a.actor_optimizer.second, &a.actor),
    );
    push_net(
        &mut tensors,
        "critic_adam_m",
        &adam_as_net(&a.critic_optimizer.first, &a.critic),
    );
    push_net(
        &mut tensors,
        "critic_adam_v",
        &adam_as_net(&a.critic_optimizer.second, &a.critic),
    );
    if let Some(twin) = &a.twin {
        push_net(&mut tensors, "critic2", &twin.critic);
        push_net(&mut tensors, "target_critic2", &twin.target);
        push_net(
            &mut tensors,
            "critic2_adam_m",
            &adam_as_net(&twin.optimizer.first, &twin.critic),
        );
        push_net(
            &mut tensors,
            "critic2_adam_v",
            &adam_as_net(&twin.optimizer.second, &twin.critic),
        );
    }
    for (v, name) in a.values.iter().zip(VALUE_NETS) {
        push_net(&mut tensors, name[0], &v.value);
        push_net(&mut tensors, name[1], &v.target);
        push_net(
            &mut tensors,
            name[2],
            &adam_as_net(&v.optimizer.first, &v.value),
        );
        push_net(
            &mut tensors,
            name[3],
            &adam_as_net(&v.optimizer.second, &v.value),
        );
    }
    let mut meta = net_meta("skyherd-trainer-checkpoint-v1", &a.actor);
    for (v, name) in a.values.iter().zip(VALUE_NETS) {
        meta.insert(name[4].into(), v.optimizer.step.to_string());
    }
    if let Some(twin) = &a.twin {
        meta.insert("critic2_adam_step".into(), twin.optimizer.step.to_string());
    }
    meta.insert("updates".into(), a.updates.to_string());
    meta.insert("actor_adam_step".into(), a.actor_optimizer.step.to_string());
    meta.insert(
        "critic_adam_step".into(),
        a.critic_optimizer.step.to_string(),
    );
    meta.insert(
        "progress".into(),
        toml::to_string(&checkpoint.progress).unwrap_or_default(),
    );
    meta.insert("config".into(), checkpoint.config.to_toml());
    serialize(&tensors, meta)
}

/// The metadata every file carries: its format and the network's shape.
fn net_meta(format: &str, net: &MultiTaskMlp) -> HashMap<String, String> {
    let mut meta = HashMap::new();
    meta.insert("format".into(), format.into());
    meta.insert("tasks".into(), net.tasks().to_string());
    meta.insert("shared_layers".into(), net.shared.len().to_string());
    meta
}

/// `(name, shape, f32 bytes)` tensors and metadata as safetensors bytes.
fn serialize(
    tensors: &[(String, Vec<usize>, Vec<u8>)],
    meta: HashMap<String, String>,
) -> Result<Vec<u8>, CheckpointError> {
    let views = tensors
        .iter()
        .map(|(name, shape, bytes)| {
            TensorView::new(Dtype::F32, shape.clone(), bytes)
                .map(|v| (name.clone(), v))
                .map_err(|e| CheckpointError::Format(e.to_string()))
        })
        .collect::<Result<Vec<_>, _>>()?;
    let bytes = safetensors::serialize(views, &Some(meta))
        .map_err(|e| CheckpointError::Format(e.to_string()))?;
    canonical_header(&bytes)
}

/// The same safetensors file with its JSON header's keys in sorted order. `safetensors`
/// writes the metadata map in `HashMap` order, which changes from process to process; sorted,
/// the same checkpoint is the same bytes every time (runs are compared by their files).
fn canonical_header(bytes: &[u8]) -> Result<Vec<u8>, CheckpointError> {
    let format = |what: &str| CheckpointError::Format(format!("serialized header: {what}"));
    let length_bytes: [u8; 8] = bytes
        .get(..8)
        .and_then(|b| b.try_into().ok())
        .ok_or_else(|| format("shorter than its length field"))?;
    let length = usize::try_from(u64::from_le_bytes(length_bytes))
        .map_err(|_| format("length does not fit"))?;
    let end = 8usize
        .checked_add(length)
        .filter(|&e| e <= bytes.len())
        .ok_or_else(|| format("length past the end"))?;
    // serde_json's map is a BTreeMap (no `preserve_order`): parsing sorts every object.
    let header: serde_json::Value =
        serde_json::from_slice(&bytes[8..end]).map_err(|e| format(&e.to_string()))?;
    let mut json = serde_json::to_vec(&header).map_err(|e| format(&e.to_string()))?;
    // The data after the header stays 8-byte aligned, padded with spaces as safetensors does.
    json.resize(json.len().next_multiple_of(8), b' ');
    let mut out = Vec::with_capacity(8 + json.len() + bytes.len() - end);
    out.extend_from_slice(&(json.len() as u64).to_le_bytes());
    out.extend_from_slice(&json);
    out.extend_from_slice(&bytes[end..]);
    Ok(out)
}

fn read_dense(st: &SafeTensors<'_>, name: &str) -> Result<Dense, CheckpointError> {
    let tensor = |n: String| -> Result<(Vec<usize>, Vec<f32>), CheckpointError> {
        let t = st
            .tensor(&n)
            .map_err(|_| CheckpointError::Tensor(n.clone()))?;
        if t.dtype() != Dtype::F32 {
            return Err(CheckpointError::Tensor(n));
        }
        let values = t
            .data()
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        Ok((t.shape().to_vec(), values))
    };
    let (wshape, weights) = tensor(format!("{name}.weight"))?;
    let (bshape, bias) = tensor(format!("{name}.bias"))?;
    if wshape.len() != 2 || bshape != [wshape[0]] {
        return Err(CheckpointError::Tensor(name.to_owned()));
    }
    Ok(Dense {
        inputs: wshape[1],
        outputs: wshape[0],
        weights,
        bias,
    })
}

fn read_net(
    st: &SafeTensors<'_>,
    prefix: &str,
    tasks: usize,
    shared: usize,
    output_activation: Activation,
) -> Result<MultiTaskMlp, CheckpointError> {
    let group = |part: &str, count: usize| {
        (0..count)
            .map(|i| read_dense(st, &format!("{prefix}.{part}.{i}")))
            .collect::<Result<Vec<_>, _>>()
    };
    Ok(MultiTaskMlp {
        task_inputs: group("task_inputs", tasks)?,
        shared: group("shared", shared)?,
        task_outputs: group("task_outputs", tasks)?,
        output_activation,
    })
}

/// Parses safetensors bytes written by [`to_bytes`].
pub fn from_bytes(bytes: &[u8]) -> Result<Checkpoint, CheckpointError> {
    let (_, header) =
        SafeTensors::read_metadata(bytes).map_err(|e| CheckpointError::Format(e.to_string()))?;
    let meta = header
        .metadata()
        .clone()
        .ok_or(CheckpointError::Metadata("__metadata__"))?;
    let st = SafeTensors::deserialize(bytes).map_err(|e| CheckpointError::Format(e.to_string()))?;
    let number = |key: &'static str| -> Result<u64, CheckpointError> {
        meta.get(key)
            .and_then(|v| v.parse().ok())
            .ok_or(CheckpointError::Metadata(key))
    };
    let tasks = number("tasks")? as usize;
    let shared = number("shared_layers")? as usize;
    let config = meta
        .get("config")
        .and_then(|t| TrainConfig::from_toml_str(t).ok())
        .ok_or(CheckpointError::Metadata("config"))?;
    let progress: Progress = meta
        .get("progress")
        .and_then(|t| toml::from_str(t).ok())
        .ok_or(CheckpointError::Metadata("progress"))?;
    let net = |prefix: &str, act| read_net(&st, prefix, tasks, shared, act);
    let actor = net("actor", Activation::Tanh)?;
    let critic = net("critic", Activation::Identity)?;
    let mut agent = Agent::from_networks(actor, critic, config.ddpg);
    agent.target_actor = net("target_actor", Activation::Tanh)?;
    agent.target_critic = net("target_critic", Activation::Identity)?;
    let adam = |m: &str, v: &str, act, step: u64, lr: f32| -> Result<Adam, CheckpointError> {
        Ok(Adam {
            config: AdamConfig {
                learning_rate: lr,
                ..AdamConfig::default()
            },
            step,
            first: net(m, act)?.layers().cloned().collect(),
            second: net(v, act)?.layers().cloned().collect(),
        })
    };
    agent.actor_optimizer = adam(
        "actor_adam_m",
        "actor_adam_v",
        Activation::Tanh,
        number("actor_adam_step")?,
        config.ddpg.actor_learning_rate,
    )?;
    agent.critic_optimizer = adam(
        "critic_adam_m",
        "critic_adam_v",
        Activation::Identity,
        number("critic_adam_step")?,
        config.ddpg.critic_learning_rate,
    )?;
    if config.ddpg.twin_critics {
        let mut twin = TwinCritic::new(
            net("critic2", Activation::Identity)?,
            config.ddpg.critic_learning_rate,
        );
        twin.target = net("target_critic2", Activation::Identity)?;
        twin.optimizer = adam(
            "critic2_adam_m",
            "critic2_adam_v",
            Activation::Identity,
            number("critic2_adam_step")?,
            config.ddpg.critic_learning_rate,
        )?;
        agent.twin = Some(Box::new(twin));
    }
    if config.ddpg.advantage_scale > 0.0 {
        let count = 1 + usize::from(config.ddpg.twin_critics);
        for name in &VALUE_NETS[..count] {
            let mut value = StateValue::new(
                net(name[0], Activation::Identity)?,
                config.ddpg.critic_learning_rate,
            );
            value.target = net(name[1], Activation::Identity)?;
            value.optimizer = adam(
                name[2],
                name[3],
                Activation::Identity,
                number(name[4])?,
                config.ddpg.critic_learning_rate,
            )?;
            agent.values.push(value);
        }
    }
    agent.updates = number("updates")?;
    agent.reseed_noise();
    Ok(Checkpoint {
        agent,
        progress,
        config,
    })
}

/// Writes only the actor (`actor.*` tensors), e.g. the float reference of a shipped model.
pub fn save_actor(path: &Path, actor: &MultiTaskMlp) -> Result<(), CheckpointError> {
    let mut tensors = Vec::new();
    push_net(&mut tensors, "actor", actor);
    let bytes = serialize(&tensors, net_meta("skyherd-trainer-actor-v1", actor))?;
    std::fs::write(path, bytes).map_err(|source| CheckpointError::Io {
        path: path.to_owned(),
        source,
    })
}

/// Reads an actor written by [`save_actor`] (or the actor of a full checkpoint).
pub fn load_actor(path: &Path) -> Result<MultiTaskMlp, CheckpointError> {
    let bytes = std::fs::read(path).map_err(|source| CheckpointError::Io {
        path: path.to_owned(),
        source,
    })?;
    let (_, header) =
        SafeTensors::read_metadata(&bytes).map_err(|e| CheckpointError::Format(e.to_string()))?;
    let meta = header
        .metadata()
        .clone()
        .ok_or(CheckpointError::Metadata("__metadata__"))?;
    let number = |key: &'static str| -> Result<usize, CheckpointError> {
        meta.get(key)
            .and_then(|v| v.parse().ok())
            .ok_or(CheckpointError::Metadata(key))
    };
    let st =
        SafeTensors::deserialize(&bytes).map_err(|e| CheckpointError::Format(e.to_string()))?;
    read_net(
        &st,
        "actor",
        number("tasks")?,
        number("shared_layers")?,
        Activation::Tanh,
    )
}

/// Writes a checkpoint atomically (temporary file, then rename), so a run killed mid-write
/// leaves the previous checkpoint intact.
pub(crate) fn save(path: &Path, checkpoint: &Checkpoint) -> Result<(), CheckpointError> {
    let bytes = to_bytes(checkpoint)?;
    let io = |source| CheckpointError::Io {
        path: path.to_owned(),
        source,
    };
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(io)?;
    }
    let tmp = path.with_extension("safetensors.tmp");
    std::fs::write(&tmp, bytes).map_err(io)?;
    std::fs::rename(&tmp, path).map_err(io)
}

/// Reads a checkpoint file.
pub fn load(path: &Path) -> Result<Checkpoint, CheckpointError> {
    let bytes = std::fs::read(path).map_err(|source| CheckpointError::Io {
        path: path.to_owned(),
        source,
    })?;
    from_bytes(&bytes)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ddpg::NetworkConfig;
    use crate::replay::Batch;
    use rand::SeedableRng;

    #[test]
    fn save_and_load_round_trip_everything() {
        round_trip(false);
    }

    #[test]
    fn a_td3_checkpoint_keeps_its_twin_critic() {
        round_trip(true);
    }

    #[test]
    fn an_advantage_critic_checkpoint_keeps_its_state_values() {
        round_trip_with(false, 0.1);
        round_trip_with(true, 0.1);
    }

    fn round_trip(twin_critics: bool) {
        round_trip_with(twin_critics, 0.0);
    }

    fn round_trip_with(twin_critics: bool, advantage_scale: f32) {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let mut config = TrainConfig {
            seed: 99,
            ..TrainConfig::default()
        };
        config.ddpg.twin_critics = twin_critics;
        config.ddpg.advantage_scale = advantage_scale;
        let network = NetworkConfig {
            hidden: 8,
            shared_layers: 2,
        };
        let mut agent = Agent::new(5, 2, network, config.ddpg, &mut rng);
        // Take a few steps so targets, moments and counters differ from a fresh agent.
        let batch = Batch {
            size: 2,
            obs: vec![0.1, 0.2, 0.3, 0.4, 0.5, -0.1, -0.2, -0.3, -0.4, -0.5],
            actions: vec![0.5, 0.0, -0.5, 0.1, 0.2, 0.3],
            rewards: vec![-1.0, 2.0],
            next_obs: vec![0.0; 10],
            continues: vec![1.0, 0.0],
            ..Batch::default()
        };
        for _ in 0..3 {
            agent.update(&[batch.clone(), batch.clone()]);
        }
        let progress = Progress {
            env_steps: 1234,
            episodes: 7,
            warm_start_done: true,
            wall_time_s: 12.5,
            best_success: 0.75,
            best_time_ratio: 3.25,
            task_resets: [1, 0],
            task_reset_env_steps: [600, 0],
            task_best_since_reset: [0.125, 0.5],
            task_last_pass_env_steps: [900, 1200],
            task_latest_success: [0.375, 1.0],
            task_env_steps: [617, 617],
        };
        let original = Checkpoint {
            agent,
            progress,
            config,
        };
        let dir = std::env::temp_dir().join(format!(
            "skyherd-ckpt-{}-{twin_critics}-{advantage_scale}",
            std::process::id()
        ));
        let path = dir.join("c.safetensors");
        save(&path, &original).expect("save");
        let back = load(&path).expect("load");
        let (a, b) = (&original.agent, &back.agent);
        assert_eq!(a.actor, b.actor);
        assert_eq!(a.critic, b.critic);
        assert_eq!(a.target_actor, b.target_actor);
        assert_eq!(a.target_critic, b.target_critic);
        assert_eq!(a.actor_optimizer, b.actor_optimizer);
        assert_eq!(a.critic_optimizer, b.critic_optimizer);
        assert_eq!(a.updates, b.updates);
        assert_eq!(a.twin.is_some(), twin_critics);
        if let (Some(x), Some(y)) = (&a.twin, &b.twin) {
            assert_eq!(x.critic, y.critic);
            assert_eq!(x.target, y.target);
            assert_eq!(x.optimizer, y.optimizer);
        }
        assert_eq!(a.twin.is_some(), b.twin.is_some());
        let values = if advantage_scale > 0.0 {
            1 + usize::from(twin_critics)
        } else {
            0
        };
        assert_eq!(a.values.len(), values);
        assert_eq!(b.values.len(), values);
        for (x, y) in a.values.iter().zip(&b.values) {
            assert_eq!(x.value, y.value);
            assert_eq!(x.target, y.target);
            assert_eq!(x.optimizer, y.optimizer);
            assert_ne!(
                x.value, x.target,
                "three updates moved the value off its target"
            );
        }
        assert_eq!(back.progress, original.progress);
        assert_eq!(back.config, original.config);
        assert!(from_bytes(&to_bytes(&original).expect("bytes")[..100]).is_err());
        let actor_path = dir.join("actor.safetensors");
        std::fs::create_dir_all(&dir).expect("dir");
        save_actor(&actor_path, &original.agent.actor).expect("save actor");
        assert_eq!(
            load_actor(&actor_path).expect("load actor"),
            original.agent.actor
        );
        assert_eq!(
            load_actor(&path).expect("actor of a full checkpoint"),
            original.agent.actor
        );
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn the_same_checkpoint_is_the_same_bytes() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(6);
        let network = NetworkConfig {
            hidden: 4,
            shared_layers: 1,
        };
        let checkpoint = Checkpoint {
            agent: Agent::new(3, 2, network, TrainConfig::default().ddpg, &mut rng),
            progress: Progress::default(),
            config: TrainConfig::default(),
        };
        // Every call builds its metadata in a fresh HashMap, whose order varies with its seed.
        let first = to_bytes(&checkpoint).expect("bytes");
        for _ in 0..16 {
            assert!(to_bytes(&checkpoint).expect("bytes") == first);
        }
        let (length, header) = SafeTensors::read_metadata(&first).expect("a safetensors file");
        assert_eq!(length % 8, 0, "data stays 8-byte aligned");
        let meta = header.metadata().clone().expect("metadata");
        assert_eq!(meta["format"], "skyherd-trainer-checkpoint-v1");
        let text = std::str::from_utf8(&first[8..8 + length]).expect("utf-8");
        let keys: Vec<usize> = ["\"config\"", "\"format\"", "\"progress", "\"tasks\""]
            .iter()
            .map(|k| text.find(k).unwrap_or_else(|| panic!("{k} in {text:.200}")))
            .collect();
        assert!(keys.is_sorted(), "metadata keys in order: {keys:?}");
        assert!(from_bytes(&first).is_ok());
    }

    #[test]
    fn progress_from_before_task_resets_reads_as_none() {
        let old = "env_steps = 500\nepisodes = 3\nwarm_start_done = false\nwall_time_s = 1.5\n\
                   best_success = 0.25\nbest_time_ratio = 4.0\n";
        let p: Progress = toml::from_str(old).expect("an older checkpoint's progress");
        assert_eq!(p.env_steps, 500);
        assert_eq!(p.task_resets, [0, 0]);
        assert_eq!(p.task_reset_env_steps, [0, 0]);
        assert_eq!(p.task_last_pass_env_steps, [0, 0]);
        assert_eq!(p.task_latest_success, [0.0, 0.0]);
    }
}
