//! Progress bars for long work: live bars on a terminal, periodic log lines otherwise, nothing
//! when quiet (tests).

use std::io::IsTerminal;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use indicatif::{ProgressBar, ProgressStyle};

/// How progress is shown.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Progress {
    mode: Mode,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Mode {
    Bars,
    Lines,
    Quiet,
}

impl Progress {
    /// Bars on a terminal, log lines on a pipe.
    pub fn auto() -> Self {
        Self {
            mode: if std::io::stderr().is_terminal() {
                Mode::Bars
            } else {
                Mode::Lines
            },
        }
    }

    /// No output.
    pub fn quiet() -> Self {
        Self { mode: Mode::Quiet }
    }

    /// A bar of `len` steps labelled `prefix`.
    pub fn bar(&self, len: u64, prefix: &str) -> Bar {
        match self.mode {
            Mode::Bars => {
                let pb = ProgressBar::new(len);
                pb.set_style(
                    ProgressStyle::with_template(
                        "{prefix:>8} [{elapsed_precise}] {wide_bar} {pos}/{len} {msg} (eta {eta})",
                    )
                    .expect("valid template"),
                );
                pb.set_prefix(prefix.to_string());
                Bar {
                    inner: Inner::Bar(pb),
                }
            }
            Mode::Lines => Bar {
                inner: Inner::Lines(Mutex::new(Lines {
                    prefix: prefix.to_string(),
                    len,
                    pos: 0,
                    msg: String::new(),
                    start: Instant::now(),
                    last: Instant::now(),
                })),
            },
            Mode::Quiet => Bar {
                inner: Inner::Quiet,
            },
        }
    }

    /// A message line (warnings, where the outputs are).
    pub fn note(&self, msg: &str) {
        if self.mode != Mode::Quiet {
            eprintln!("{msg}");
        }
    }
}

/// One progress bar.
pub struct Bar {
    inner: Inner,
}

enum Inner {
    Bar(ProgressBar),
    Lines(Mutex<Lines>),
    Quiet,
}

struct Lines {
    prefix: String,
    len: u64,
    pos: u64,
    msg: String,
    start: Instant,
    last: Instant,
}

impl Lines {
    fn maybe_print(&mut self, force: bool) {
        if force || self.last.elapsed() >= Duration::from_secs(10) {
            self.last = Instant::now();
            eprintln!(
                "{}: {}/{} {} ({:.1} s)",
                self.prefix,
                self.pos,
                self.len,
                self.msg,
                self.start.elapsed().as_secs_f64()
            );
        }
    }
}

impl Bar {
    /// Sets the position.
    pub fn set_position(&self, pos: u64) {
        match &self.inner {
            Inner::Bar(b) => b.set_position(pos),
            Inner::Lines(l) => {
                let mut l = l.lock().expect("lock");
                l.pos = pos;
                l.maybe_print(false);
            }
            Inner::Quiet => {}
        }
    }

    /// Advances by `n`.
    pub fn inc(&self, n: u64) {
        match &self.inner {
            Inner::Bar(b) => b.inc(n),
            Inner::Lines(l) => {
                let mut l = l.lock().expect("lock");
                l.pos += n;
                l.maybe_print(false);
            }
            Inner::Quiet => {}
        }
    }

    /// Sets the live message (e.g. the loss).
    pub fn set_message(&self, msg: String) {
        match &self.inner {
            Inner::Bar(b) => b.set_message(msg),
            Inner::Lines(l) => l.lock().expect("lock").msg = msg,
            Inner::Quiet => {}
        }
    }

    /// Marks the bar done, at its length (a search's length is its most candidates; one that
    /// settles early ends there too).
    pub fn finish(&self) {
        match &self.inner {
            Inner::Bar(b) => b.finish(),
            Inner::Lines(l) => {
                let mut l = l.lock().expect("lock");
                l.pos = l.len;
                l.maybe_print(true)
            }
            Inner::Quiet => {}
        }
    }

    /// Leaves the bar where it stopped (on an error).
    pub(crate) fn abandon(&self) {
        match &self.inner {
            Inner::Bar(b) => b.abandon(),
            Inner::Lines(l) => l.lock().expect("lock").maybe_print(true),
            Inner::Quiet => {}
        }
    }
}
