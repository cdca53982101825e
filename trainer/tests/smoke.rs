//! A seconds-long training run through every phase (demonstrations, imitation, critic
//! pretraining, MTDDPG, evaluation, evolution, checkpoints, log, plot), then `--resume`, then
//! export.

use skyherd_model::Task;
use skyherd_trainer::checkpoint;
use skyherd_trainer::config::TrainConfig;
use skyherd_trainer::eval::EvalScenario;
use skyherd_trainer::export::{export, parity, record_observations};
use skyherd_trainer::network::MultiTaskMlp;
use skyherd_trainer::report::read_log;
use skyherd_trainer::train::{FINALISTS_MEAN_EVAL_FILE, Quiet, choose_finalist, train};

fn tiny_config(dir: &std::path::Path) -> TrainConfig {
    TrainConfig::from_toml_str(&format!(
        r#"
        seed = 11
        output_dir = "{}"
        [network]
        hidden = 16
        [training]
        env_steps = 300
        envs = 2
        episode_step_limit = 40
        learning_starts = 50
        wall_clock_limit_s = 60.0
        [curriculum]
        stages = [{{ from_progress = 0.0, targets = [2, 4], herders = [1, 2] }}]
        [warm_start]
        episodes_per_task = 1
        imitation_updates = 300
        critic_updates = 50
        [eval]
        every_updates = 100
        episodes = 1
        scenarios = [["driving", 4, 2], ["collecting", 4, 2]]
        [evolution]
        generations = 2
        population = 2
        step_limit = 40
        check_every = 1
        check_rounds = 1
        scenarios = [
          {{ task = "driving", targets = 4, herders = 2, room = true, episodes = 1 }},
          {{ task = "collecting", targets = 4, herders = 2, episodes = 1 }},
        ]
        "#,
        dir.display()
    ))
    .expect("tiny config")
}

#[test]
fn tiny_training_runs_resumes_and_exports() {
    let dir = std::env::temp_dir().join(format!("skyherd-smoke-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let mut config = tiny_config(&dir);

    let first = train(&config, None, &mut Quiet).expect("training runs");
    assert!(first.progress.warm_start_done);
    assert!(first.progress.env_steps >= 300, "{:?}", first.progress);
    assert!(first.seconds_per_update.is_finite());
    for file in [
        "best.safetensors",
        "evolved.safetensors",
        "last.safetensors",
        "log.csv",
        "curve.png",
    ] {
        assert!(dir.join(file).exists(), "{file} written");
    }
    let log = read_log(&dir.join("log.csv")).expect("log");
    assert!(log.iter().any(|r| r.phase == 0), "imitation rows");
    assert!(log.iter().any(|r| r.phase == 2), "evaluation rows");
    assert_eq!(
        log.iter().filter(|r| r.phase == 3).count(),
        4,
        "two evolution generations per task"
    );
    let evolution = first.evolution.as_ref().expect("evolution ran");
    assert_eq!(evolution.tasks.len(), 2);
    for (task, before, after) in &evolution.tasks {
        assert!(
            after.fitness >= before.fitness,
            "{task:?} kept the best check"
        );
    }
    let evolved = checkpoint::load(&evolution.checkpoint).expect("evolved checkpoint");
    let best = checkpoint::load(&dir.join("best.safetensors")).expect("best checkpoint");
    assert_eq!(evolved.agent.actor.shared, best.agent.actor.shared);
    assert_eq!(evolved.agent.critic, best.agent.critic);
    // Imitation reduces its loss.
    let imitation: Vec<f64> = log
        .iter()
        .filter(|r| r.phase == 0)
        .map(|r| r.actor_loss)
        .collect();
    assert!(imitation.last() < imitation.first(), "{imitation:?}");

    // Resume: the counters continue from the checkpoint, the warm start is not repeated.
    let last = checkpoint::load(&dir.join("last.safetensors")).expect("last checkpoint");
    let updates_before = last.agent.updates;
    config.training.env_steps = 500;
    let second = train(&config, Some(last), &mut Quiet).expect("resumed training runs");
    assert!(second.progress.env_steps >= 500);
    let resumed = checkpoint::load(&dir.join("last.safetensors")).expect("checkpoint");
    assert!(resumed.agent.updates > updates_before);

    // Export the best actor and compare the quantized actor with it on recorded observations.
    let best = checkpoint::load(&dir.join("best.safetensors")).expect("best checkpoint");
    let scenarios = [EvalScenario {
        task: Task::Driving,
        targets: 4,
        herders: 2,
    }];
    let obs = record_observations(&best.agent.actor, &scenarios, 2, 7, 60, 1).expect("record");
    let bytes = export(&best.agent.actor, 5.0, &obs).expect("export");
    let p = parity(&best.agent.actor, &bytes, &obs).expect("parity");
    assert!(p.rms_component < 0.05, "{p:?}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn the_same_seed_trains_the_same_actor() {
    let run = |tag: &str| {
        let dir = std::env::temp_dir().join(format!("skyherd-seed-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let mut config = tiny_config(&dir);
        config.training.env_steps = 150;
        config.evolution.enabled = false;
        train(&config, None, &mut Quiet).expect("training runs");
        let c = checkpoint::load(&dir.join("last.safetensors")).expect("checkpoint");
        let _ = std::fs::remove_dir_all(&dir);
        c.agent
    };
    let (a, b) = (run("a"), run("b"));
    assert_eq!(a.actor, b.actor);
    assert_eq!(a.critic, b.critic);
    assert!(a.updates > 0);
}

/// From scratch with every learner option on (TD3, n-step, OU noise, planar, random-waypoint
/// warm-up, the audited reward), as the two arms of the ablation, then the ablation report.
#[test]
fn from_scratch_td3_arms_train_and_the_ablation_reports_them() {
    let dir = std::env::temp_dir().join(format!("skyherd-ablation-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let base = TrainConfig::from_toml_str(
        r#"
        seed = 5
        [network]
        hidden = 16
        [ddpg]
        gamma = 0.995
        twin_critics = true
        target_noise = 0.2
        n_step = 3
        exploration = "ornstein_uhlenbeck"
        planar = true
        [training]
        env_steps = 400
        envs = 2
        episode_step_limit = 40
        learning_starts = 50
        random_warmup_steps = 100
        wall_clock_limit_s = 60.0
        [curriculum]
        stages = [{ from_progress = 0.0, targets = [2, 4], herders = [2] }]
        [warm_start]
        enabled = false
        [reward]
        kind = "audited"
        [eval]
        every_task_env_steps = 100
        episodes = 1
        scenarios = [["driving", 4, 2], ["collecting", 4, 2]]
        [evolution]
        enabled = false
        "#,
    )
    .expect("from-scratch config");
    for (arm, tasks, steps) in [
        ("mtddpg", vec![Task::Driving, Task::Collecting], 400),
        ("single-driving", vec![Task::Driving], 200),
    ] {
        let mut config = base.clone();
        config.output_dir = dir.join(format!("{arm}-seed5"));
        config.training.tasks = tasks;
        config.training.env_steps = steps;
        let out = train(&config, None, &mut Quiet).expect("from-scratch training runs");
        assert!(!out.progress.warm_start_done);
        let csv = std::fs::read_to_string(config.output_dir.join("eval.csv")).expect("eval.csv");
        // Every 100 steps per task, plus the final evaluation.
        assert!(csv.lines().count() >= 3, "{csv}");
        if arm == "single-driving" {
            assert!(!csv.contains("collecting"), "{csv}");
        }
    }
    let report = skyherd_trainer::ablation::report(&dir, &dir.join("report")).expect("report");
    assert!(
        report.contains("| driving | 200 | mtddpg | 1 |"),
        "{report}"
    );
    assert!(
        report.contains("| driving | 200 | single | 1 |"),
        "{report}"
    );
    assert!(
        report.contains("- driving:") && report.contains("no verdict"),
        "{report}"
    );
    assert!(dir.join("report/curve-driving.png").exists());
    assert!(dir.join("report/curve-driving.svg").exists());
    let _ = std::fs::remove_dir_all(&dir);
}

/// The options of the second from-scratch config (a centralised critic, the onboard flight
/// rules, the driving-distance curriculum, the progress shaping and the approach term) train
/// together, and a fine-tune starts from an actor file: the critic alone learns first, then the
/// actor moves. A fine-tune whose actor does not fit is refused with the widths named.
#[test]
fn a_centralised_fine_tune_starts_from_its_actor_and_learns_the_critic_first() {
    let dir = std::env::temp_dir().join(format!("skyherd-finetune-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let text = |actor: &std::path::Path, critic_only: u64| {
        format!(
            r#"
            seed = 6
            output_dir = "{}"
            [network]
            hidden = 16
            [ddpg]
            gamma = 0.995
            twin_critics = true
            n_step = 3
            planar = true
            centralised_critic = true
            critic_max_others = 3
            policy_frequency = 1
            [training]
            env_steps = 300
            envs = 2
            episode_step_limit = 40
            learning_starts = 50
            flight_rules = true
            wall_clock_limit_s = 60.0
            [curriculum]
            stages = [{{ from_progress = 0.0, targets = [2, 4], herders = [3] }}]
            [curriculum.driving_goal_distance]
            first_share = 0.3
            full_at_progress = 0.5
            [warm_start]
            enabled = false
            [reward]
            kind = "audited"
            [reward.audited]
            shaping = 5.0
            shaping_form = "progress"
            approach = 1.0
            [fine_tune]
            actor = "{}"
            critic_only_env_steps = {critic_only}
            [eval]
            every_task_env_steps = 150
            episodes = 1
            scenarios = [["driving", 4, 3], ["collecting", 4, 3]]
            [evolution]
            enabled = false
            "#,
            dir.display(),
            actor.display()
        )
    };
    // The actor to start from: a tiny run's.
    let mut source = tiny_config(&dir.join("source"));
    source.training.env_steps = 100;
    source.evolution.enabled = false;
    source.warm_start.enabled = false;
    train(&source, None, &mut Quiet).expect("source run");
    let actor_file = dir.join("start.actor.safetensors");
    let start = checkpoint::load(&dir.join("source/last.safetensors")).expect("source checkpoint");
    checkpoint::save_actor(&actor_file, &start.agent.actor).expect("save actor");

    // Critic only for the whole run: the actor is exactly the file's.
    let frozen = TrainConfig::from_toml_str(&text(&actor_file, 10_000)).expect("config");
    train(&frozen, None, &mut Quiet).expect("fine-tune runs");
    let after = checkpoint::load(&dir.join("last.safetensors")).expect("checkpoint");
    assert_eq!(
        after.agent.actor, start.agent.actor,
        "critic-only steps leave the actor"
    );
    assert!(after.agent.updates > 0);
    assert_eq!(
        after.agent.context_dim(),
        after.agent.obs_dim() + 3,
        "centralised"
    );

    // Then the actor moves.
    let _ = std::fs::remove_file(dir.join("last.safetensors"));
    let moving = TrainConfig::from_toml_str(&text(&actor_file, 150)).expect("config");
    train(&moving, None, &mut Quiet).expect("fine-tune runs");
    let after = checkpoint::load(&dir.join("last.safetensors")).expect("checkpoint");
    assert_ne!(
        after.agent.actor, start.agent.actor,
        "the actor learns after the critic"
    );

    // An actor of another width is refused, naming both.
    let mut narrow = start.agent.actor.clone();
    narrow = skyherd_trainer::network::MultiTaskMlp::new(
        skyherd_trainer::network::MlpShape::actor(narrow.inputs() - 5, 16, 1),
        &mut <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(1),
    );
    let narrow_file = dir.join("narrow.actor.safetensors");
    checkpoint::save_actor(&narrow_file, &narrow).expect("save");
    let refused = TrainConfig::from_toml_str(&text(&narrow_file, 0)).expect("config");
    let err = train(&refused, None, &mut Quiet).expect_err("a misfit actor");
    assert!(err.to_string().contains("inputs"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Random restarts: two candidates seeded apart train for their trial, the better one on the
/// training-time evaluation goes on, and the steps of both count towards the run's budget.
#[test]
fn restarts_try_candidates_and_continue_the_best_within_the_budget() {
    let dir = std::env::temp_dir().join(format!("skyherd-restarts-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let mut config = tiny_config(&dir);
    config.warm_start.enabled = false;
    config.evolution.enabled = false;
    config.training.env_steps = 600;
    config.training.restart_candidates = 2;
    config.training.restart_trial_env_steps = 200;
    config.validate().expect("a valid restarts config");
    let outcome = train(&config, None, &mut Quiet).expect("training runs");
    let record: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(dir.join("restarts.json")).expect("restarts.json"),
    )
    .expect("JSON");
    let winner = record["winner"].as_u64().expect("a winner") as usize;
    assert!(winner < 2);
    assert_eq!(record["candidates"].as_array().map(Vec::len), Some(2));
    assert_ne!(
        record["candidates"][0]["seed"],
        record["candidates"][1]["seed"]
    );
    // The winner's own steps: the budget less the loser's trial.
    assert_eq!(record["winner_env_steps"], 400);
    assert!(outcome.progress.env_steps >= 400, "{:?}", outcome.progress);
    assert!(outcome.progress.env_steps < 600, "{:?}", outcome.progress);
    for i in 0..2 {
        let candidate = dir.join(format!("candidate-{i}"));
        assert!(candidate.join("last.safetensors").exists(), "candidate {i}");
        let c = checkpoint::load(&candidate.join("last.safetensors")).expect("checkpoint");
        if i == winner {
            assert!(c.progress.env_steps >= 400);
        } else {
            assert!(
                (200..400).contains(&c.progress.env_steps),
                "{:?}",
                c.progress
            );
        }
    }
    // More trial than budget is refused, naming the field.
    config.training.restart_trial_env_steps = 300;
    let err = config.validate().expect_err("refused").to_string();
    assert!(err.contains("restart_trial_env_steps"), "{err}");
    std::fs::remove_dir_all(&dir).ok();
}

/// With finalists on, the best few checkpoints by the check are kept on disk and no more, the
/// end of the run copies the one the second episode set prefers to `best.safetensors`, and a
/// resumed run goes on with the finalists it had.
#[test]
fn finalists_are_kept_and_one_is_chosen_on_the_second_set() {
    let dir = std::env::temp_dir().join(format!("skyherd-finalists-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let mut config = TrainConfig::from_toml_str(&format!(
        r#"
        seed = 7
        output_dir = "{}"
        [network]
        hidden = 16
        [ddpg]
        planar = true
        [training]
        env_steps = 400
        envs = 2
        episode_step_limit = 40
        learning_starts = 50
        random_warmup_steps = 100
        wall_clock_limit_s = 60.0
        [curriculum]
        stages = [{{ from_progress = 0.0, targets = [2], herders = [2] }}]
        [warm_start]
        enabled = false
        [reward]
        kind = "audited"
        [eval]
        every_task_env_steps = 50
        episodes = 1
        scenarios = [["driving", 2, 2], ["collecting", 2, 2]]
        finalists = 2
        final_episodes = 2
        final_seed_base = 6_000_000_000
        [evolution]
        enabled = false
        "#,
        dir.display()
    ))
    .expect("finalists config");
    let on_disk = |dir: &std::path::Path| {
        let mut steps: Vec<u64> = std::fs::read_dir(dir)
            .expect("output dir")
            .filter_map(|e| {
                let name = e.ok()?.file_name().into_string().ok()?;
                name.strip_prefix("finalist-")?
                    .strip_suffix(".safetensors")?
                    .parse()
                    .ok()
            })
            .collect();
        steps.sort_unstable();
        steps
    };
    // Learning is the same step for step with finalists off: the choice only reads the actors.
    let mut plain = config.clone();
    plain.eval.finalists = 0;
    plain.output_dir = dir.join("plain");
    train(&plain, None, &mut Quiet).expect("training without finalists runs");
    for steps in [400, 600] {
        config.training.env_steps = steps;
        let resume = (steps > 400)
            .then(|| checkpoint::load(&dir.join("last.safetensors")).expect("last checkpoint"));
        train(&config, resume, &mut Quiet).expect("training with finalists runs");
        let csv = std::fs::read_to_string(dir.join("finalists.csv")).expect("finalists.csv");
        let listed = skyherd_trainer::finalists::from_csv(&csv);
        assert_eq!(listed.len(), 2, "{csv}");
        let mut listed_steps: Vec<u64> = listed.iter().map(|f| f.env_steps).collect();
        listed_steps.sort_unstable();
        assert_eq!(on_disk(&dir), listed_steps, "{csv}");
        // Every finalist has its final-set score and exactly one was chosen.
        let chosen: Vec<&str> = csv
            .lines()
            .skip(1)
            .filter(|l| l.ends_with(",true"))
            .collect();
        assert_eq!(chosen.len(), 1, "{csv}");
        assert_eq!(
            csv.lines().filter(|l| l.ends_with(",false")).count(),
            1,
            "{csv}"
        );
        let winner: u64 = chosen[0].split(',').next().unwrap().parse().unwrap();
        assert_eq!(
            std::fs::read(dir.join("best.safetensors")).unwrap(),
            std::fs::read(skyherd_trainer::finalists::file(&dir, winner)).unwrap()
        );
        let rows = std::fs::read_to_string(dir.join("finalists-eval.csv")).expect("rows");
        // One row per finalist and scenario, each of the second set's two episodes.
        assert_eq!(rows.lines().count(), 1 + 2 * 2, "{rows}");
        assert!(
            rows.lines()
                .skip(1)
                .all(|l| l.split(',').nth(5) == Some("2")),
            "{rows}"
        );
        if steps == 400 {
            let with = checkpoint::load(&dir.join("last.safetensors")).expect("last");
            let without =
                checkpoint::load(&plain.output_dir.join("last.safetensors")).expect("last");
            assert_eq!(with.agent.actor, without.agent.actor);
            assert_eq!(with.agent.critic, without.agent.critic);
            assert!(!plain.output_dir.join("finalists.csv").exists());
        }
    }
    // The choice again on the finished run, with the mean of both finalists as a candidate
    // (what `skyherd-trainer choose --average-finalists-from 0` does).
    let listed = skyherd_trainer::finalists::from_csv(
        &std::fs::read_to_string(dir.join("finalists.csv")).expect("finalists.csv"),
    );
    let scenarios: Vec<EvalScenario> = config.eval.scenario_list();
    config.eval.average_finalists_from = Some(0.0);
    config
        .validate()
        .expect("averaging two finalists is allowed");
    let kept = choose_finalist(&config, &dir, &listed, &scenarios, &mut Quiet)
        .expect("the choice runs")
        .expect("something is kept");
    let actors: Vec<_> = listed
        .iter()
        .map(|f| {
            checkpoint::load(&skyherd_trainer::finalists::file(&dir, f.env_steps))
                .expect("finalist")
                .agent
                .actor
        })
        .collect();
    let mean_file = dir.join(skyherd_trainer::finalists::MEAN_FILE);
    let mean = checkpoint::load(&mean_file).expect("the mean is saved");
    let want = MultiTaskMlp::mean_of(&actors.iter().collect::<Vec<_>>()).expect("same shapes");
    assert_eq!(mean.agent.actor, want);
    let csv = std::fs::read_to_string(dir.join("finalists.csv")).expect("finalists.csv");
    assert_eq!(csv.lines().count(), 1 + 3, "{csv}");
    assert_eq!(
        csv.lines().filter(|l| l.ends_with(",true")).count(),
        1,
        "{csv}"
    );
    let mean_line = csv.lines().last().expect("the mean's line");
    assert!(mean_line.starts_with("mean of "), "{csv}");
    // The finalists read back without the mean (a resumed run goes on with them alone).
    assert_eq!(skyherd_trainer::finalists::from_csv(&csv), listed);
    let best = std::fs::read(dir.join("best.safetensors")).expect("best");
    if kept.check.is_none() {
        assert!(mean_line.ends_with(",true"), "{csv}");
        assert_eq!(best, std::fs::read(&mean_file).expect("mean"));
        assert_eq!(kept.env_steps.len(), 2);
    } else {
        assert_eq!(
            best,
            std::fs::read(skyherd_trainer::finalists::file(&dir, kept.env_steps[0]))
                .expect("finalist")
        );
    }
    let mean_rows =
        std::fs::read_to_string(dir.join(FINALISTS_MEAN_EVAL_FILE)).expect("the mean's rows");
    assert_eq!(mean_rows.lines().count(), 1 + 2, "{mean_rows}");
    // Without averaging, the choice is the finalists' alone again and the mean's files go.
    config.eval.average_finalists_from = None;
    let again = choose_finalist(&config, &dir, &listed, &scenarios, &mut Quiet)
        .expect("the choice runs")
        .expect("something is kept");
    assert!(again.check.is_some());
    assert!(!mean_file.exists());
    assert!(!dir.join(FINALISTS_MEAN_EVAL_FILE).exists());
    let _ = std::fs::remove_dir_all(&dir);
}
