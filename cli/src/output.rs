//! Standard output and error that a closed reader (`lbctl list | head -1`, `lbctl ... 2>&1 |
//! head -0`) ends quietly instead of panicking: `println!` and `eprintln!` panic on a broken
//! pipe, and lbctl keeps no unsafe code to reset SIGPIPE.

use std::io::{self, Write};
use std::sync::atomic::{AtomicBool, Ordering};

static CLOSED: AtomicBool = AtomicBool::new(false);

/// Writes `args` (and a newline) to standard output. Once the reader has gone, the rest of the
/// output is dropped and the command runs on to its own exit code; another write error is
/// said once on standard error.
pub fn write(args: std::fmt::Arguments<'_>, newline: bool) {
    if CLOSED.load(Ordering::Relaxed) {
        return;
    }
    let mut out = io::stdout().lock();
    let result = out
        .write_fmt(args)
        .and_then(|()| {
            if newline {
                out.write_all(b"\n")
            } else {
                Ok(())
            }
        })
        .and_then(|()| out.flush());
    if let Err(e) = result {
        CLOSED.store(true, Ordering::Relaxed);
        if e.kind() != io::ErrorKind::BrokenPipe {
            write_err(format_args!("lbctl: cannot write to standard output: {e}"));
        }
    }
}

/// Writes `args` and a newline to standard error; a closed or failing standard error drops
/// it (there is nowhere left to say so).
pub fn write_err(args: std::fmt::Arguments<'_>) {
    let mut err = io::stderr().lock();
    let _ = err.write_fmt(args).and_then(|()| err.write_all(b"\n"));
}

/// Whether standard output's reader went away.
pub fn closed() -> bool {
    CLOSED.load(Ordering::Relaxed)
}

/// `println!` that survives a closed pipe.
#[macro_export]
macro_rules! outln {
    () => {
        $crate::output::write(format_args!(""), true)
    };
    ($($arg:tt)*) => {
        $crate::output::write(format_args!($($arg)*), true)
    };
}

/// `eprintln!` that survives a closed standard error.
#[macro_export]
macro_rules! errln {
    ($($arg:tt)*) => {
        $crate::output::write_err(format_args!($($arg)*))
    };
}

/// `print!` that survives a closed pipe.
#[macro_export]
macro_rules! out {
    ($($arg:tt)*) => {
        $crate::output::write(format_args!($($arg)*), false)
    };
}

/// Asks `question` on the terminal and reads the answer: `true` only when the operator typed
/// `id` back (anything else, or an empty line, is a no). `Err` when no answer can be read.
pub fn confirm_id(question: &str, id: u64) -> io::Result<bool> {
    use io::BufRead;
    write(format_args!("{question}? type its id to confirm: "), false);
    let _ = io::stdout().flush();
    let mut line = String::new();
    io::stdin().lock().read_line(&mut line)?;
    Ok(line.trim() == id.to_string())
}
