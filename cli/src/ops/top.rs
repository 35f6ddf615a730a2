//! `lbctl top`: the fleet, live: each leaderboard's queue with waits and estimated starts, the
//! submissions running with their progress, capacity and cost so far, the GPU nodes paid for
//! and idle, today's cost and the recent failures, redrawn in place until `q`.

use std::collections::HashMap;
use std::fmt::Write as _;
use std::io::IsTerminal;
use std::time::Duration;

use clap::Args;
use lb_aws::dynamo::RecordStatus;
use lb_cluster::fleet::GpuFleet;
use lb_domain::capacity::cost::CapacityType;
use lb_domain::capacity::queue::{EntryState, StartEstimate};
use lb_pipeline::cluster::Clusters;

use super::list::{age, estimates, parse_time, short_age, short_estimate, shorten};
use super::{places, Place};
use crate::deployment::{clean, Deployment, DeploymentArgs, Record, ScanFilter};
use crate::error::{CliError, Result};

/// Failures a screen lists, the latest first.
const RECENT_FAILURES: usize = 5;

/// `lbctl top` options.
#[derive(Debug, Clone, Args)]
#[command(after_help = "Examples:
  lbctl top                        # every leaderboard, redrawn every 5 s; q quits, r redraws now
  lbctl top --leaderboard 2.0 --interval 30
  lbctl top --once                 # one screen as text (also when the output is no terminal)

Records and queues from DynamoDB, GPU nodes from each leaderboard's cluster (EKS, or
LB_KUBECONFIG; listing nodes takes an operator's access). What cannot be read is said on the
screen. Against a local stack: the environment `lbctl local run` prints.")]
pub struct Top {
    /// Only this leaderboard (a key of the settings' `leaderboards`, e.g. `2.0`).
    #[arg(long, value_name = "LEADERBOARD")]
    pub leaderboard: Option<String>,
    /// Seconds between two screens.
    #[arg(long, default_value_t = 5, value_parser = clap::value_parser!(u64).range(1..=3600))]
    pub interval: u64,
    /// One screen as text, then exit.
    #[arg(long)]
    pub once: bool,
    #[command(flatten)]
    pub deployment: DeploymentArgs,
}

/// One look at the fleet.
#[derive(Debug, Clone, Default)]
struct Screen {
    /// When (UTC, as shown).
    at: String,
    /// Each leaderboard shown.
    boards: Vec<Board>,
    /// What could not be read (records, queues), said above the boards.
    notes: Vec<String>,
}

/// A cluster's GPU nodes (its name, what they hold, their price an hour), or why they could
/// not be read.
type Gpus = std::result::Result<(String, GpuFleet, Option<f64>), String>;

/// Each queued submission's place, and the estimated starts, by leaderboard and id.
type Queues<'a> = (
    &'a HashMap<(String, u64), Place>,
    &'a HashMap<(String, u64), StartEstimate>,
);

/// One leaderboard's part of a screen.
#[derive(Debug, Clone, Default)]
struct Board {
    name: String,
    waiting: Vec<Waiting>,
    running: Vec<Running>,
    /// The cluster's GPU nodes, or why not.
    gpus: Option<Gpus>,
    today: Today,
    failures: Vec<Failure>,
}

#[derive(Debug, Clone)]
struct Waiting {
    id: u64,
    team: String,
    waited: Option<time::Duration>,
    place: Option<usize>,
    /// Held by its team's cap (`true`) or waiting for GPUs.
    team_cap: Option<bool>,
    starts_in: Option<StartEstimate>,
}

#[derive(Debug, Clone)]
struct Running {
    id: u64,
    team: String,
    routes: (Option<u64>, Option<u64>),
    running_for: Option<time::Duration>,
    capacity: &'static str,
    dollars: Option<f64>,
}

#[derive(Debug, Clone, Default, PartialEq)]
struct Today {
    dollars: f64,
    spot_share: Option<f64>,
    run_again_hours: f64,
    finished: usize,
    failed: usize,
    cancelled: usize,
}

#[derive(Debug, Clone)]
struct Failure {
    id: u64,
    team: String,
    ended: String,
    why: String,
}

/// `lbctl top`.
pub async fn top(args: Top) -> Result<u8> {
    let deployment = Deployment::load(&args.deployment).await?;
    // Fail on a leaderboard the settings do not name before drawing anything.
    deployment.leaderboards(args.leaderboard.as_deref())?;
    let clusters = Clusters::from_env(&deployment.sdk);
    if args.once || !std::io::stdout().is_terminal() {
        let screen = look(&deployment, &args, &clusters).await;
        out!("{}", render(&screen, 120).join("\n") + "\n");
        return Ok(0);
    }
    live(&deployment, &args, &clusters).await
}

/// Redraws the screen every `interval` until a key or a signal says to stop; the terminal is
/// given back as it was however it ends.
async fn live(deployment: &Deployment, args: &Top, clusters: &Clusters) -> Result<u8> {
    use tokio::signal::unix::{signal, SignalKind};
    let _terminal = terminal::Screen::enter()?;
    let mut keys = terminal::keys();
    // A closed SSH session (hangup) or a kill ends it as `q` does.
    let mut hangup = signal(SignalKind::hangup()).map_err(CliError::Terminal)?;
    let mut term = signal(SignalKind::terminate()).map_err(CliError::Terminal)?;
    let interval = Duration::from_secs(args.interval);
    loop {
        let screen = tokio::select! {
            screen = look(deployment, args, clusters) => screen,
            key = keys.recv() => match key {
                Some(terminal::Key::Quit) | None => return Ok(0),
                Some(_) => continue,
            },
            _ = hangup.recv() => return Ok(0),
            _ = term.recv() => return Ok(0),
        };
        terminal::draw(&screen_lines(&screen, args))?;
        let next = tokio::time::Instant::now() + interval;
        loop {
            tokio::select! {
                key = keys.recv() => match key {
                    Some(terminal::Key::Quit) | None => return Ok(0),
                    Some(terminal::Key::Resized) => terminal::draw(&screen_lines(&screen, args))?,
                    Some(terminal::Key::Refresh) => break,
                },
                _ = tokio::time::sleep_until(next) => break,
                _ = hangup.recv() => return Ok(0),
                _ = term.recv() => return Ok(0),
            }
        }
    }
}

/// The screen's lines for the terminal's width, with the keys on the first.
fn screen_lines(screen: &Screen, args: &Top) -> Vec<String> {
    let (width, _) = crossterm::terminal::size().unwrap_or((120, 40));
    let mut lines = render(screen, usize::from(width));
    if let Some(first) = lines.first_mut() {
        let keys = format!(" -- every {} s; q quits, r redraws", args.interval);
        *first = cut(&(first.clone() + &keys), usize::from(width));
    }
    lines
}

/// Reads everything a screen shows; what cannot be read becomes a note on it.
async fn look(deployment: &Deployment, args: &Top, clusters: &Clusters) -> Screen {
    let now = time::OffsetDateTime::now_utc();
    let mut screen = Screen {
        at: now
            .format(time::macros::format_description!(
                "[year]-[month]-[day] [hour]:[minute]:[second] UTC"
            ))
            .unwrap_or_default(),
        ..Screen::default()
    };
    let only = args.leaderboard.as_deref();
    let found = match deployment.records(only, ScanFilter::All).await {
        Ok(found) => found,
        Err(e) => {
            screen.notes.push(format!("records not readable: {e}"));
            return screen;
        }
    };
    for table in &found.truncated {
        screen
            .notes
            .push(format!("{table}: the scan stopped at its limit"));
    }
    let places = places(deployment, only).await.unwrap_or_else(|e| {
        screen.notes.push(format!("queues not readable: {e}"));
        HashMap::new()
    });
    let waiting: Vec<&Record> = found.records.iter().filter(|r| is_waiting(r)).collect();
    let starts = estimates(deployment, &waiting, &places).await;
    let Ok(boards) = deployment.leaderboards(only) else {
        return screen;
    };
    for (name, settings) in boards {
        let records: Vec<&Record> = (found.records.iter())
            .filter(|r| r.leaderboard == name)
            .collect();
        let mut board = board(name, &records, (&places, &starts), now);
        board.gpus = Some(match clusters.connect(settings).await {
            Ok(cluster) => match cluster.gpu_fleet().await {
                Ok(fleet) => {
                    let hourly = hourly(&fleet, &deployment.settings.prices);
                    Ok((settings.cluster.clone(), fleet, hourly))
                }
                Err(e) => Err(format!("{}: nodes not readable: {e}", settings.cluster)),
            },
            Err(e) => Err(format!(
                "{}: not reachable: {}",
                settings.cluster,
                e.chain()
            )),
        });
        screen.boards.push(board);
    }
    screen
}

/// Claimed, not running yet.
fn is_waiting(r: &Record) -> bool {
    matches!(
        r.status,
        Some(RecordStatus::Submitted | RecordStatus::Resuming)
    )
}

/// A leaderboard's board from its records, the queues' places and the estimated starts.
fn board(
    name: &str,
    records: &[&Record],
    (places, starts): Queues<'_>,
    now: time::OffsetDateTime,
) -> Board {
    let team = |r: &Record| clean(r.team_name.as_deref().unwrap_or("-"));
    let mut board = Board {
        name: name.to_owned(),
        ..Board::default()
    };
    for r in records {
        let Some(id) = r.submission_id else { continue };
        let key = (name.to_owned(), id);
        if is_waiting(r) {
            let place = places.get(&key);
            board.waiting.push(Waiting {
                id,
                team: team(r),
                waited: age(r, now),
                place: place.map(|p| p.ahead as usize + 1),
                team_cap: place.map(|p| p.state == EntryState::Waiting),
                starts_in: starts.get(&key).copied(),
            });
        } else if r.status == Some(RecordStatus::Running) {
            let usage = r.usage();
            board.running.push(Running {
                id,
                team: team(r),
                routes: r.routes,
                running_for: r
                    .start_time
                    .as_deref()
                    .and_then(parse_time)
                    .map(|t| now - t),
                capacity: usage
                    .as_ref()
                    .map_or("-", |u| capacity(u.spot, u.gpu_seconds)),
                dollars: usage.and_then(|u| u.dollars),
            });
        }
    }
    board
        .waiting
        .sort_by_key(|w| (w.place.unwrap_or(usize::MAX), w.id));
    board
        .running
        .sort_by_key(|r| std::cmp::Reverse(r.running_for));
    board.today = today(records, now);
    board.failures = failures(records);
    board
}

/// Spot, on-demand or both, by the GPU-seconds held.
fn capacity(spot: u64, held: u64) -> &'static str {
    match (spot, held) {
        (_, 0) => "-",
        (s, h) if s >= h => "Spot",
        (0, _) => "on-demand",
        _ => "mixed",
    }
}

/// What the records say of today (UTC): the GPU cost of the runs that ended today and of those
/// running, and how today's ended.
fn today(records: &[&Record], now: time::OffsetDateTime) -> Today {
    let mut today = Today::default();
    let (mut spot, mut held) = (0u64, 0u64);
    for r in records {
        let ended_today = (r.end_time.as_deref())
            .and_then(parse_time)
            .is_some_and(|t| t.date() == now.date());
        let running = r.status == Some(RecordStatus::Running);
        if !(ended_today || running) {
            continue;
        }
        if let Some(u) = r.usage() {
            today.dollars += u.dollars.unwrap_or(0.0);
            today.run_again_hours += u.run_again as f64 / 3600.0;
            spot += u.spot;
            held += u.gpu_seconds;
        }
        if ended_today {
            match r.status {
                Some(RecordStatus::Finished) => today.finished += 1,
                Some(RecordStatus::Failed) => today.failed += 1,
                Some(RecordStatus::Cancelled) => today.cancelled += 1,
                _ => {}
            }
        }
    }
    today.spot_share = (held > 0).then(|| spot as f64 / held as f64);
    today
}

/// The latest failures, newest first.
fn failures(records: &[&Record]) -> Vec<Failure> {
    let mut failed: Vec<&&Record> = records
        .iter()
        .filter(|r| r.status == Some(RecordStatus::Failed))
        .collect();
    // NB: `2024-03-07 10:31:02 UTC` sorts as it reads.
    failed.sort_by(|a, b| b.end_time.cmp(&a.end_time));
    failed
        .into_iter()
        .take(RECENT_FAILURES)
        .filter_map(|r| {
            Some(Failure {
                id: r.submission_id?,
                team: clean(r.team_name.as_deref().unwrap_or("-")),
                ended: clean(r.end_time.as_deref().unwrap_or("-")),
                why: clean(r.error.as_deref().unwrap_or("-")),
            })
        })
        .collect()
}

/// What the GPU nodes cost an hour at the settings' prices; none when one has no price.
fn hourly(
    fleet: &GpuFleet,
    prices: &std::collections::BTreeMap<String, lb_domain::capacity::cost::InstancePrice>,
) -> Option<f64> {
    fleet
        .nodes
        .iter()
        .map(|n| {
            let price = prices.get(&n.kind.instance_type)?;
            Some(match n.kind.capacity {
                CapacityType::Spot => price.spot,
                CapacityType::OnDemand | CapacityType::Unknown => price.on_demand,
            })
        })
        .sum()
}

/// `text` cut to `width` characters.
fn cut(text: &str, width: usize) -> String {
    text.chars().take(width).collect()
}

/// The screen as lines of at most `width` characters.
fn render(screen: &Screen, width: usize) -> Vec<String> {
    let mut out = vec![format!("lbctl top -- {}", screen.at)];
    out.extend(screen.notes.iter().map(|n| format!("! {n}")));
    for board in &screen.boards {
        out.push(String::new());
        render_board(board, &mut out);
    }
    out.iter().map(|l| cut(l, width)).collect()
}

fn render_board(b: &Board, out: &mut Vec<String>) {
    out.push(format!("LEADERBOARD {}", b.name));
    let held_by_cap = b
        .waiting
        .iter()
        .filter(|w| w.team_cap == Some(true))
        .count();
    let longest = b.waiting.iter().filter_map(|w| w.waited).max();
    out.push(format!(
        "  queue    {} waiting ({} held by their team's cap, {} for GPUs){}",
        b.waiting.len(),
        held_by_cap,
        b.waiting.len() - held_by_cap,
        longest.map_or(String::new(), |l| format!("; longest {}", short_age(l))),
    ));
    // From +0.0: an empty f64 sum is -0.0, which prints as "$-0.00".
    let so_far = b
        .running
        .iter()
        .filter_map(|r| r.dollars)
        .fold(0.0, |a, d| a + d);
    out.push(format!(
        "  running  {} submissions; ${so_far:.2} so far",
        b.running.len()
    ));
    out.push(format!("  GPUs     {}", gpus_line(b.gpus.as_ref())));
    let t = &b.today;
    out.push(format!(
        "  today    ${:.2} on GPUs{}, {:.1} GPU-hours run again; {} finished, {} failed, {} cancelled",
        t.dollars,
        t.spot_share
            .map_or(String::new(), |s| format!(" ({:.0}% on Spot)", s * 100.0)),
        t.run_again_hours,
        t.finished,
        t.failed,
        t.cancelled
    ));
    render_waiting(&b.waiting, out);
    render_running(&b.running, out);
    render_failures(&b.failures, out);
}

fn render_waiting(waiting: &[Waiting], out: &mut Vec<String>) {
    if waiting.is_empty() {
        return;
    }
    out.push(String::new());
    out.push(format!(
        "  {:<10} {:<24} {:>7} {:>5}  {:<9} {:>9}",
        "WAITING", "TEAM", "WAITED", "PLACE", "HELD BY", "STARTS IN"
    ));
    for w in waiting {
        out.push(format!(
            "  {:<10} {:<24} {:>7} {:>5}  {:<9} {:>9}",
            w.id,
            shorten(&w.team, 24),
            w.waited.map_or("-".into(), short_age),
            w.place.map_or("-".into(), |p| p.to_string()),
            match w.team_cap {
                Some(true) => "team cap",
                Some(false) => "GPUs",
                None => "-",
            },
            w.starts_in.map_or("-".into(), short_estimate),
        ));
    }
}

fn render_running(running: &[Running], out: &mut Vec<String>) {
    if running.is_empty() {
        return;
    }
    out.push(String::new());
    out.push(format!(
        "  {:<10} {:<24} {:>7} {:>7}  {:<9} {:>9}",
        "RUNNING", "TEAM", "ROUTES", "FOR", "CAPACITY", "COST"
    ));
    for r in running {
        let count = |n: Option<u64>| n.map_or("-".into(), |n| n.to_string());
        out.push(format!(
            "  {:<10} {:<24} {:>7} {:>7}  {:<9} {:>9}",
            r.id,
            shorten(&r.team, 24),
            format!("{}/{}", count(r.routes.0), count(r.routes.1)),
            r.running_for.map_or("-".into(), short_age),
            r.capacity,
            r.dollars.map_or("-".into(), |d| format!("${d:.2}")),
        ));
    }
}

fn render_failures(failures: &[Failure], out: &mut Vec<String>) {
    if failures.is_empty() {
        return;
    }
    out.push(String::new());
    out.push("  RECENT FAILURES".into());
    for f in failures {
        out.push(format!(
            "  {:<10} {:<24} {}  {}",
            f.id,
            shorten(&f.team, 24),
            f.ended,
            f.why
        ));
    }
}

fn gpus_line(gpus: Option<&Gpus>) -> String {
    let (cluster, fleet, hourly) = match gpus {
        None => return "-".into(),
        Some(Err(why)) => return why.clone(),
        Some(Ok(found)) => found,
    };
    let (paid, held) = (fleet.gpus(), fleet.held());
    let idle = paid - held;
    let nodes = fleet.nodes.len();
    let mut line = format!(
        "{cluster}: {nodes} node{} ({} Spot), {paid} GPUs paid for, {held} held, {idle} idle",
        if nodes == 1 { "" } else { "s" },
        fleet.spot_nodes()
    );
    if paid > 0 {
        let _ = write!(line, " ({:.0}%)", f64::from(idle) * 100.0 / f64::from(paid));
    }
    let draining = fleet.nodes.iter().filter(|n| n.draining).count();
    if draining > 0 {
        let _ = write!(line, ", {draining} draining");
    }
    if let Some(h) = hourly {
        let _ = write!(line, "; ${h:.2} an hour");
    }
    line
}

/// The terminal as `lbctl top` uses it: raw keys, the alternate screen, no cursor; all given
/// back on drop, however the view ends.
mod terminal {
    use std::io::Write as _;

    use crossterm::event::{Event, KeyCode, KeyEvent, KeyEventKind, KeyModifiers};
    use crossterm::{cursor, execute, terminal};

    use crate::error::{CliError, Result};

    /// What a key (or the window) asks.
    #[derive(Debug, Clone, Copy, PartialEq, Eq)]
    pub(super) enum Key {
        /// `q`, Esc or Ctrl-C.
        Quit,
        /// `r`: look again now.
        Refresh,
        /// The window changed size: draw again.
        Resized,
    }

    /// The terminal taken over until dropped.
    pub(super) struct Screen;

    impl Screen {
        pub(super) fn enter() -> Result<Screen> {
            terminal::enable_raw_mode().map_err(CliError::Terminal)?;
            // From here on, dropped on any error: raw mode never outlives the view.
            let screen = Screen;
            execute!(
                std::io::stdout(),
                terminal::EnterAlternateScreen,
                cursor::Hide
            )
            .map_err(CliError::Terminal)?;
            Ok(screen)
        }
    }

    impl Drop for Screen {
        fn drop(&mut self) {
            let _ = execute!(
                std::io::stdout(),
                cursor::Show,
                terminal::LeaveAlternateScreen
            );
            let _ = terminal::disable_raw_mode();
        }
    }

    /// The keys pressed, read on a thread of their own (a blocked read there keeps nothing
    /// from ending).
    pub(super) fn keys() -> tokio::sync::mpsc::Receiver<Key> {
        let (tx, rx) = tokio::sync::mpsc::channel(16);
        std::thread::spawn(move || {
            let wait = std::time::Duration::from_millis(200);
            while !tx.is_closed() {
                let Ok(true) = crossterm::event::poll(wait) else {
                    continue;
                };
                let key = match crossterm::event::read() {
                    Ok(Event::Key(key)) if key.kind != KeyEventKind::Release => of(key),
                    Ok(Event::Resize(..)) => Some(Key::Resized),
                    Ok(_) => None,
                    Err(_) => Some(Key::Quit),
                };
                if let Some(key) = key {
                    if tx.blocking_send(key).is_err() {
                        break;
                    }
                }
            }
        });
        rx
    }

    fn of(key: KeyEvent) -> Option<Key> {
        match key.code {
            KeyCode::Char('q' | 'Q') | KeyCode::Esc => Some(Key::Quit),
            KeyCode::Char('c') if key.modifiers.contains(KeyModifiers::CONTROL) => Some(Key::Quit),
            KeyCode::Char('r' | 'R') => Some(Key::Refresh),
            _ => None,
        }
    }

    /// Draws `lines` over the last screen, each line cleared to its end (no flicker).
    pub(super) fn draw(lines: &[String]) -> Result<()> {
        let mut out = std::io::stdout().lock();
        let mut text = String::from("\x1b[H");
        for line in lines {
            text.push_str(line);
            text.push_str("\x1b[K\r\n");
        }
        text.push_str("\x1b[J");
        out.write_all(text.as_bytes())
            .and_then(|()| out.flush())
            .map_err(CliError::Terminal)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_screen_shows_the_queue_the_runs_the_gpus_and_today_within_its_width() {
        let board = Board {
            name: "2.0".into(),
            waiting: vec![Waiting {
                id: 12,
                team: "Team Two".into(),
                waited: Some(time::Duration::minutes(42)),
                place: Some(1),
                team_cap: Some(true),
                starts_in: None,
            }],
            running: vec![Running {
                id: 11,
                team: "Team One".into(),
                routes: (Some(3), Some(20)),
                running_for: Some(time::Duration::minutes(75)),
                capacity: capacity(10, 10),
                dollars: Some(1.5),
            }],
            gpus: Some(Err("leaderboard-20: not reachable".into())),
            today: Today {
                dollars: 2.0,
                finished: 1,
                ..Today::default()
            },
            failures: Vec::new(),
        };
        let screen = Screen {
            at: "2026-11-30 12:00:00 UTC".into(),
            boards: vec![board],
            notes: Vec::new(),
        };
        let lines = render(&screen, 80);
        let text = lines.join("\n");
        assert!(lines.iter().all(|l| l.chars().count() <= 80), "{text}");
        assert!(
            text.contains(
                "queue    1 waiting (1 held by their team's cap, 0 for GPUs); longest 42m"
            ),
            "{text}"
        );
        assert!(text.contains("12         Team Two"), "{text}");
        assert!(text.contains("team cap"), "{text}");
        assert!(text.contains("3/20"), "{text}");
        assert!(text.contains("1h15m"), "{text}");
        assert!(text.contains("Spot"), "{text}");
        assert!(text.contains("leaderboard-20: not reachable"), "{text}");
        assert!(text.contains("today    $2.00 on GPUs"), "{text}");
        assert_eq!(capacity(0, 10), "on-demand");
        assert_eq!(capacity(4, 10), "mixed");
        assert_eq!(capacity(0, 0), "-");
    }
}
