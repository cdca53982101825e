//! The mission's other processes: the command lines of the ground station and of one onboard
//! daemon per drone, built from the SITL world they will fly in, and a guard that ends a
//! child process when dropped. Building a command starts nothing; [`spawn`] does.

use std::fs::File;
use std::io;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};

use skyherd_onboard::Task;
use skyherd_sim::{Scenario, World};

use crate::mission::AutopilotLink;

/// Where the mission's files and programs are.
#[derive(Clone, Debug)]
pub struct LaunchPlan {
    /// The `skyherd-ground` executable.
    pub ground: PathBuf,
    /// The `skyherd-onboard` executable.
    pub daemon: PathBuf,
    /// Run each daemon through this command line (e.g. `qemu-aarch64 -L /usr/aarch64-linux-gnu`).
    pub daemon_wrapper: Option<String>,
    /// The model file the daemons fly.
    pub model: PathBuf,
    /// The mission's key folder ([`KeyFolder`]): `drone-N.key` per drone, `fleet.key`.
    pub keys: PathBuf,
    /// Output folder (ground `.tlog` and CSV, daemon logs).
    pub out: PathBuf,
    /// Fault injection for the ground: `START,DURATION` of uplink cut.
    pub cut_uplink: Option<String>,
    /// The ground stops this many wall seconds after the last scan and prints its summary.
    pub ground_idle_timeout_s: f64,
    /// The daemons keep at least this far apart (`--separation-m`); `None`: the rule is off.
    pub keep_apart_m: Option<f64>,
    /// The daemons land after this long of stale uplink in flight (`--land-after-s`), s; 0:
    /// never.
    pub land_after_s: f64,
    /// The daemons take off to this height (`--takeoff-alt-m`), m.
    pub takeoff_alt_m: f64,
    /// The vehicles' braking (`--braking DECELERATION,LAG`), when they fly a dynamics model.
    pub braking: Option<(f64, f64)>,
}

/// The ground station's command: it listens for the fleet at `fleet`, and sends each drone's
/// uplink to `127.0.0.1:uplink_ports[i]`. Its stdout (the JSON summary) is piped.
pub fn ground_command(
    plan: &LaunchPlan,
    scenario: &Scenario,
    world: &World,
    fleet: SocketAddr,
    uplink_ports: &[u16],
    scan_period_s: f64,
) -> Command {
    let task = match world.task {
        Task::Driving => "driving",
        Task::Collecting => "collecting",
    };
    let mut cmd = Command::new(&plan.ground);
    cmd.arg("mission")
        .arg("--fleet")
        .arg(format!("udpin:{fleet}"))
        .args(["--task", task])
        .arg("--goal")
        .arg(format!("{},{}", world.goal.center[0], world.goal.center[1]))
        .arg("--goal-radius")
        .arg(world.goal.radius.to_string())
        .arg("--area")
        .arg(format!(
            "{},{},{}",
            world.area.width, world.area.depth, world.area.ceiling
        ))
        .arg("--max-speed")
        .arg(scenario.limits.herder.to_string())
        .arg("--targets")
        .arg(world.targets.len().to_string())
        .arg("--measurement-std")
        .arg(scenario.noise.sensing_std.max(1e-3).to_string())
        .arg("--scan-period")
        .arg(scan_period_s.to_string())
        .arg("--key-dir")
        .arg(&plan.keys)
        .arg("--fleet-key")
        .arg(plan.keys.join(KeyFolder::FLEET))
        .arg("--tlog")
        .arg(plan.out.join("ground.tlog"))
        .arg("--csv")
        .arg(plan.out.join("ground.csv"))
        .arg("--idle-timeout")
        .arg(plan.ground_idle_timeout_s.to_string())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit());
    if let Some(cut) = &plan.cut_uplink {
        cmd.arg("--cut-uplink").arg(cut);
    }
    for (i, port) in uplink_ports.iter().enumerate() {
        cmd.arg("--drone")
            .arg(format!("{}=udpout:127.0.0.1:{port}", i + 1));
    }
    cmd
}

/// Drone `index`'s daemon (system id `index + 1`): it flies the autopilot over `autopilot` and
/// hears the ground on `127.0.0.1:uplink_port`, on the simulator's clock. Its log goes to
/// `daemon-{index + 1}.log` in the output folder.
///
/// # Errors
/// When the log file cannot be created or the wrapper is empty.
pub fn daemon_command(
    plan: &LaunchPlan,
    scenario: &Scenario,
    index: usize,
    autopilot: &AutopilotLink,
    uplink_port: u16,
) -> io::Result<Command> {
    let log = File::create(plan.out.join(format!("daemon-{}.log", index + 1)))?;
    let mut cmd = match &plan.daemon_wrapper {
        Some(wrapper) => {
            let mut parts = wrapper.split_whitespace();
            let program = parts.next().ok_or_else(|| {
                io::Error::new(io::ErrorKind::InvalidInput, "--daemon-wrapper is empty")
            })?;
            let mut cmd = Command::new(program);
            cmd.args(parts).arg(&plan.daemon);
            cmd
        }
        None => Command::new(&plan.daemon),
    };
    cmd.arg("run")
        .arg("--model")
        .arg(&plan.model)
        .arg("--system-id")
        .arg((index + 1).to_string())
        .arg("--herder-index")
        .arg(index.to_string())
        .arg("--autopilot")
        .arg(&autopilot.address)
        .arg("--ground")
        .arg(format!("udpin:127.0.0.1:{uplink_port}"))
        .arg("--key")
        .arg(plan.keys.join(KeyFolder::drone(index + 1)))
        .arg("--replay-state")
        .arg(plan.out.join(format!("daemon-{}.replay", index + 1)))
        .arg("--sim-clock")
        .arg("--max-speed")
        .arg(scenario.limits.herder.to_string())
        .arg("--land-after-s")
        .arg(plan.land_after_s.to_string())
        .arg("--flavour")
        .arg(match autopilot.flavour {
            skyherd_link::Flavour::Px4 => "px4",
            skyherd_link::Flavour::ArduPilot => "ardupilot",
        })
        .arg("--takeoff-alt-m")
        .arg(plan.takeoff_alt_m.to_string())
        .stdout(Stdio::null())
        .stderr(log);
    if autopilot.signed {
        cmd.arg("--autopilot-key")
            .arg(plan.keys.join(KeyFolder::FLEET));
    }
    if !autopilot.lockstep {
        cmd.arg("--autopilot-runs-free");
    }
    if let Some([east, north]) = autopilot.local_origin {
        cmd.arg("--local-origin").arg(format!("{east},{north}"));
    }
    if let Some((deceleration, lag)) = plan.braking {
        cmd.arg("--braking").arg(format!("{deceleration},{lag}"));
    }
    if let Some(m) = plan.keep_apart_m {
        cmd.arg("--separation-m").arg(m.to_string());
    }
    Ok(cmd)
}

/// The mission's signing keys, in a fresh private folder outside the output folder (which is
/// meant to be shared): `drone-N.key` for each drone's uplink (the ground and that drone's
/// daemon only) and `fleet.key` (the mock autopilots, the sensor, the ground's fleet link and
/// each daemon's autopilot link). Keys come from the operating system's randomness, files are
/// created 0600 with `O_EXCL` in a folder created 0700; the folder is removed when dropped.
#[derive(Debug)]
pub struct KeyFolder {
    path: PathBuf,
    fleet: skyherd_link::SigningKey,
}

impl KeyFolder {
    /// The fleet key's file name.
    pub const FLEET: &'static str = "fleet.key";

    /// Drone `system_id`'s uplink key file name.
    pub fn drone(system_id: usize) -> String {
        format!("drone-{system_id}.key")
    }

    /// Makes the folder under `parent` (a name no one can have guessed: 64 random bits) and
    /// the keys of `drones` drones.
    ///
    /// # Errors
    /// When the folder or a key cannot be made.
    pub fn provision(parent: &std::path::Path, drones: usize) -> io::Result<Self> {
        let mut tag = [0u8; 8];
        getrandom::fill(&mut tag).map_err(|e| io::Error::other(e.to_string()))?;
        let name: String = tag.iter().map(|b| format!("{b:02x}")).collect();
        let path = parent.join(format!("skyherd-keys-{name}"));
        let mut builder = std::fs::DirBuilder::new();
        #[cfg(unix)]
        {
            use std::os::unix::fs::DirBuilderExt;
            builder.mode(0o700);
        }
        // Not recursive: an existing folder (or a symlink in its place) is an error.
        builder.create(&path)?;
        // Owned from here on, so that a failure below removes the folder again.
        let mut folder = KeyFolder {
            fleet: skyherd_link::SigningKey([0; 32]),
            path,
        };
        let write = |name: &str| -> io::Result<skyherd_link::SigningKey> {
            let key = skyherd_link::SigningKey::generate()
                .map_err(|e| io::Error::other(e.to_string()))?;
            key.write_new_file(&folder.path.join(name))
                .map_err(|e| io::Error::other(e.to_string()))?;
            Ok(key)
        };
        for id in 1..=drones {
            write(&Self::drone(id))?;
        }
        let fleet = write(Self::FLEET)?;
        folder.fleet = fleet;
        Ok(folder)
    }

    /// The folder.
    pub fn path(&self) -> &std::path::Path {
        &self.path
    }

    /// The fleet key (the simulator's autopilots and sensor sign with it).
    pub fn fleet_key(&self) -> &skyherd_link::SigningKey {
        &self.fleet
    }
}

impl Drop for KeyFolder {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.path);
    }
}

/// A child process that is killed when dropped.
#[derive(Debug, Default)]
pub struct Guard(Option<Child>);

impl Guard {
    /// The child, while it runs.
    pub fn child(&mut self) -> Option<&mut Child> {
        self.0.as_mut()
    }
}

impl Drop for Guard {
    fn drop(&mut self) {
        if let Some(child) = &mut self.0 {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// Start `command`, killed when the guard drops.
///
/// # Errors
/// When the program cannot be started.
pub fn spawn(mut command: Command) -> io::Result<Guard> {
    die_with_parent(&mut command);
    command.spawn().map(|child| Guard(Some(child)))
}

/// On Linux, the child is killed when the process that started it dies, however it dies (a
/// SIGTERM or SIGKILL runs no destructor, so the [`Guard`] alone would leave the ground and the
/// daemons running, reparented to init).
#[cfg(target_os = "linux")]
fn die_with_parent(command: &mut Command) {
    use std::os::unix::process::CommandExt;
    // SAFETY: the closure runs in the forked child before exec and calls only prctl(2), which
    // is async-signal-safe and touches no memory shared with the parent.
    #[allow(unsafe_code)]
    unsafe {
        command.pre_exec(|| {
            if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL) == -1 {
                return Err(io::Error::last_os_error());
            }
            Ok(())
        });
    }
}

#[cfg(not(target_os = "linux"))]
fn die_with_parent(_: &mut Command) {}

/// `name` beside the running program (the workspace's binaries share one folder).
///
/// # Errors
/// When the program cannot be located or `name` is not there.
pub fn sibling(name: &str) -> io::Result<PathBuf> {
    let me = std::env::current_exe()?;
    let path = me.with_file_name(name);
    if !path.exists() {
        return Err(io::Error::new(
            io::ErrorKind::NotFound,
            format!(
                "{name} not found beside {} (build it: cargo build --release -p skyherd-ground -p skyherd-daemon)",
                me.display()
            ),
        ));
    }
    Ok(path)
}

/// A UDP port on loopback that is free now, for another process to bind: below Linux's
/// ephemeral range (`net.ipv4.ip_local_port_range`, 32768 up by default), where no socket
/// bound to port 0 lands. The kernel's own pick (binding port 0 and letting go) is an
/// ephemeral port, and with 16 daemons each opening ephemeral sockets of their own one of
/// them sometimes took a daemon's uplink port first ("Address already in use").
///
/// # Errors
/// When no port in the range could be bound.
pub fn free_udp_port() -> io::Result<u16> {
    use std::sync::atomic::{AtomicU32, Ordering};
    const FIRST: u32 = 20_000;
    const COUNT: u32 = 12_000;
    static NEXT: AtomicU32 = AtomicU32::new(0);
    // Start where this process's id points, so that concurrent missions (tests) spread out.
    let start = std::process::id().wrapping_mul(2_654_435_761) % COUNT;
    for _ in 0..COUNT {
        let offset = (start + NEXT.fetch_add(1, Ordering::Relaxed)) % COUNT;
        let port = u16::try_from(FIRST + offset).unwrap_or(u16::MAX);
        if std::net::UdpSocket::bind(("127.0.0.1", port)).is_ok() {
            return Ok(port);
        }
    }
    Err(io::Error::new(
        io::ErrorKind::AddrInUse,
        "no free UDP port in 20000-31999 on loopback",
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_mission_gets_private_keys_of_its_own_that_go_with_it() {
        use std::os::unix::fs::PermissionsExt;
        let parent = std::env::temp_dir();
        let a = KeyFolder::provision(&parent, 2).expect("keys");
        let b = KeyFolder::provision(&parent, 2).expect("keys");
        assert_ne!(a.path(), b.path());
        let mode =
            |p: &std::path::Path| std::fs::metadata(p).expect("meta").permissions().mode() & 0o777;
        assert_eq!(mode(a.path()), 0o700);
        let mut seen = Vec::new();
        for folder in [&a, &b] {
            for name in [
                KeyFolder::drone(1),
                KeyFolder::drone(2),
                KeyFolder::FLEET.into(),
            ] {
                let path = folder.path().join(&name);
                assert_eq!(mode(&path), 0o600, "{name}");
                let key = skyherd_link::SigningKey::from_file(&path).expect("a key");
                assert!(!seen.contains(&key), "{name} repeats a key");
                seen.push(key);
            }
        }
        assert_eq!(
            &skyherd_link::SigningKey::from_file(&a.path().join(KeyFolder::FLEET)).expect("fleet"),
            a.fleet_key()
        );
        let gone = a.path().to_path_buf();
        drop(a);
        assert!(!gone.exists(), "the keys outlived the mission");
    }
}
