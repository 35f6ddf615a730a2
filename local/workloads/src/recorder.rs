//! CARLA's recorder as the fake server keeps it: one per server, started and stopped by a
//! client, writing the real format's header and a frame per simulated tick.
//!
//! The fake evaluator drives it with a line protocol on the RPC connection (the real client
//! speaks msgpack-RPC; the fake one only needs these three calls): `start_recorder <path>`,
//! `tick <frames>`, `stop_recorder`, each answered `ok` once done, as an RPC call returns once
//! the server did it. A relative path is CARLA's `Saved` folder (here the
//! server's working directory), as `ACarlaRecorder::GetRecorderFilename` resolves it; like
//! CARLA, the server does not create missing folders.

use std::fs::File;
use std::io::{BufWriter, Write as _};
use std::path::PathBuf;
use std::sync::{Arc, Mutex};

/// The answer to each command, once it is done: a client's call returns on it, as a
/// msgpack-RPC call to CARLA returns once the server has done it.
pub const RECORDER_DONE: &[u8] = b"ok\n";

/// The longest command line read; anything longer is not the fake evaluator's.
pub const MAX_LINE: usize = 4096;

/// The most frames one `tick` may ask for (an hour of simulated time at 20 Hz).
const MAX_TICK: u64 = 72_000;

/// Simulated seconds per frame (20 Hz).
const FRAME_SECONDS: f64 = 0.05;

/// The format version and magic every recording starts with (`CarlaRecorderInfo`).
const MAGIC: &[u8] = b"\x01\x00\x0e\x00CARLA_RECORDER";

/// Packet ids of the format (`CarlaRecorderPacketId`).
const FRAME_START: u8 = 0;
const FRAME_END: u8 = 1;
const POSITION: u8 = 6;

/// The recorder of one server, shared by its connections.
#[derive(Debug, Clone)]
pub struct Recorder {
    inner: Arc<Mutex<State>>,
}

#[derive(Debug)]
struct State {
    map: String,
    file: Option<BufWriter<File>>,
    frame: u64,
}

impl Recorder {
    /// A stopped recorder of a server on `map`.
    pub fn new(map: Option<&str>) -> Recorder {
        let map = map.map_or("Carla/Maps/Town01".to_string(), |m| {
            format!("Carla/Maps/{}", m.rsplit('/').next().unwrap_or(m))
        });
        Recorder {
            inner: Arc::new(Mutex::new(State {
                map,
                file: None,
                frame: 0,
            })),
        }
    }

    /// Does one command line; unknown lines are ignored, as a real server ignores what it
    /// cannot decode.
    pub fn command(&self, line: &str) {
        let mut state = match self.inner.lock() {
            Ok(state) => state,
            Err(poisoned) => poisoned.into_inner(),
        };
        let line = line.trim();
        if let Some(path) = line.strip_prefix("start_recorder ") {
            state.start(PathBuf::from(path.trim()));
        } else if let Some(n) = line.strip_prefix("tick ") {
            if let Ok(n) = n.trim().parse::<u64>() {
                state.tick(n.min(MAX_TICK));
            }
        } else if line == "stop_recorder" {
            state.stop();
        }
    }
}

impl State {
    fn start(&mut self, path: PathBuf) {
        self.stop();
        let file = match File::create(&path) {
            Ok(file) => file,
            Err(error) => {
                tracing::warn!(path = %path.display(), %error, "the recorder cannot write its file");
                return;
            }
        };
        let mut out = BufWriter::new(file);
        let date = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs() as i64);
        let mut header = MAGIC.to_vec();
        header.extend_from_slice(&date.to_le_bytes());
        header.extend_from_slice(&(self.map.len() as u16).to_le_bytes());
        header.extend_from_slice(self.map.as_bytes());
        if let Err(error) = out.write_all(&header) {
            tracing::warn!(%error, "the recorder cannot write its header");
            return;
        }
        tracing::info!(path = %path.display(), "recording");
        self.file = Some(out);
        self.frame = 0;
    }

    /// Appends `n` frames: each a frame start, the ego vehicle's position and a frame end.
    fn tick(&mut self, n: u64) {
        let Some(out) = self.file.as_mut() else {
            return;
        };
        for _ in 0..n {
            self.frame += 1;
            let mut packet = Vec::with_capacity(72);
            packet.push(FRAME_START);
            packet.extend_from_slice(&24u32.to_le_bytes());
            packet.extend_from_slice(&self.frame.to_le_bytes());
            packet.extend_from_slice(&FRAME_SECONDS.to_le_bytes());
            packet.extend_from_slice(&(self.frame as f64 * FRAME_SECONDS).to_le_bytes());
            // One actor's position: its id, location and rotation (6 floats).
            packet.push(POSITION);
            packet.extend_from_slice(&30u32.to_le_bytes());
            packet.extend_from_slice(&1u16.to_le_bytes());
            packet.extend_from_slice(&1u32.to_le_bytes());
            for v in [self.frame as f32 * 0.4, 0.0, 0.3, 0.0, 0.0, 0.0] {
                packet.extend_from_slice(&v.to_le_bytes());
            }
            packet.push(FRAME_END);
            packet.extend_from_slice(&0u32.to_le_bytes());
            if let Err(error) = out.write_all(&packet) {
                tracing::warn!(%error, "the recorder cannot write a frame");
                self.file = None;
                return;
            }
        }
        // NB: flushed every tick, as CARLA writes each frame: logcopy may read it any time.
        if let Err(error) = out.flush() {
            tracing::warn!(%error, "the recorder cannot flush");
        }
    }

    fn stop(&mut self) {
        if let Some(mut out) = self.file.take() {
            let _ = out.flush();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_recording_is_the_header_and_a_frame_per_tick_until_stopped() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("RouteScenario_0_rep0.log");
        let recorder = Recorder::new(Some("/Game/Carla/Maps/Town12"));
        recorder.command(&format!("start_recorder {}", path.display()));
        recorder.command("tick 20");
        recorder.command("stop_recorder");
        recorder.command("tick 20");
        let bytes = std::fs::read(&path).unwrap();
        assert!(bytes.starts_with(MAGIC));
        let map = b"Carla/Maps/Town12";
        let header = MAGIC.len() + 8 + 2 + map.len();
        assert_eq!(&bytes[header - map.len()..header], map);
        // 20 frames of 29 + 35 + 5 bytes; nothing after the stop.
        assert_eq!(bytes.len(), header + 20 * 69);
        // Nor into a folder that does not exist: CARLA does not create it.
        recorder.command(&format!(
            "start_recorder {}",
            dir.path().join("none/x.log").display()
        ));
        recorder.command("tick 1");
        assert!(!dir.path().join("none").exists());
    }
}
