//! The cluster's endpoint as EKS gives one: a load balancer in front of the API servers that
//! sends connections only to a server that is ready. Here a TCP pass-through on loopback (TLS
//! goes through untouched): while the control plane is upgraded it has no server, and a client
//! finds the endpoint closed until the new one is ready, instead of reaching a server that
//! listens before its caches (RBAC's among them) are filled.

use std::io;
use std::net::{Shutdown, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::thread;

/// The pass-through; dropping it stops taking connections.
#[derive(Debug)]
pub struct Front {
    port: u16,
    backend: Arc<Mutex<Option<u16>>>,
    stop: Arc<AtomicBool>,
}

impl Front {
    /// Listens on a free loopback port, passing connections to `backend`'s port.
    pub fn start(backend: u16) -> io::Result<Front> {
        let listener = TcpListener::bind("127.0.0.1:0")?;
        let port = listener.local_addr()?.port();
        let front = Front {
            port,
            backend: Arc::new(Mutex::new(Some(backend))),
            stop: Arc::new(AtomicBool::new(false)),
        };
        let (to, stop) = (front.backend.clone(), front.stop.clone());
        thread::Builder::new()
            .name("real-kube-front".into())
            .spawn(move || {
                for client in listener.incoming() {
                    if stop.load(Ordering::SeqCst) {
                        break;
                    }
                    let Ok(client) = client else { continue };
                    let backend = *to.lock().unwrap_or_else(PoisonError::into_inner);
                    match backend {
                        Some(port) => pass(client, port),
                        // No server behind: the connection is closed at once.
                        None => drop(client),
                    }
                }
            })?;
        Ok(front)
    }

    /// The port clients connect to.
    pub fn port(&self) -> u16 {
        self.port
    }

    /// Where connections go from now on (`None`: nowhere, each is closed); those already
    /// passed stay with their server.
    pub fn route(&self, backend: Option<u16>) {
        *self.backend.lock().unwrap_or_else(PoisonError::into_inner) = backend;
    }
}

impl Drop for Front {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        // Wakes the accept loop so that it sees the flag.
        let _ = TcpStream::connect(("127.0.0.1", self.port));
    }
}

/// Copies both ways between `client` and the server on `port` until either side closes.
fn pass(client: TcpStream, port: u16) {
    let Ok(server) = TcpStream::connect(("127.0.0.1", port)) else {
        return;
    };
    let pipe = |mut from: TcpStream, mut to: TcpStream| {
        let _ = io::copy(&mut from, &mut to);
        let _ = to.shutdown(Shutdown::Write);
        let _ = from.shutdown(Shutdown::Read);
    };
    let (Ok(client_back), Ok(server_back)) = (client.try_clone(), server.try_clone()) else {
        return;
    };
    let _ = thread::Builder::new()
        .name("real-kube-pass".into())
        .spawn(move || pipe(client, server));
    let _ = thread::Builder::new()
        .name("real-kube-pass".into())
        .spawn(move || pipe(server_back, client_back));
}
