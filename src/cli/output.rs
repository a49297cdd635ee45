//! How commands report: a progress bar on stderr, cancellation, one JSON line on stdout.

/// How often a job without a terminal says how far it is.
const LOG_EVERY: std::time::Duration = std::time::Duration::from_secs(30);

/// A progress bar on stderr fed by core's progress callback; hidden when stderr is not a
/// terminal-like sink (indicatif handles that), plain lines then instead.
pub fn progress_bar(message: &str) -> (indicatif::ProgressBar, umesh_core::Progress) {
    let pb = indicatif::ProgressBar::new(0);
    pb.set_style(
        indicatif::ProgressStyle::with_template("{spinner} {msg} [{bar:30}] {pos}/{len} ({elapsed}, eta {eta})")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    pb.set_message(message.to_string());
    let p = pb.clone();
    // Without a terminal (a log file, CI) the bar is hidden: a plain line at most every
    // LOG_EVERY instead, with the elapsed time and an estimate of what is left.
    use std::io::IsTerminal;
    let log = !std::io::stderr().is_terminal();
    let start = std::time::Instant::now();
    // (last line, any printed, the end said, the rate): a job shorter than LOG_EVERY prints
    // nothing.
    let last = std::sync::Mutex::new((start, false, false, umesh_core::Eta::new()));
    let what = message.to_string();
    let progress = umesh_core::Progress::new(move |done, total, msg| {
        if total > 0 {
            p.set_length(total);
        }
        p.set_position(done);
        if !msg.is_empty() {
            p.set_message(msg.to_string());
        }
        if log {
            let mut last = last.lock().unwrap_or_else(|e| e.into_inner());
            let now = std::time::Instant::now();
            last.3.observe(done, now);
            let finished = total > 0 && done >= total;
            if (!finished && now - last.0 >= LOG_EVERY) || (finished && last.1 && !last.2) {
                (last.0, last.1, last.2) = (now, true, finished);
                let elapsed = start.elapsed().as_secs_f64();
                let eta = match last.3.seconds_left(done, total, now) {
                    Some(left) => format!(", about {left:.0} s left"),
                    None => String::new(),
                };
                let msg = if msg.is_empty() { what.as_str() } else { msg };
                eprintln!("{msg}: {done}/{total} ({elapsed:.0} s{eta})");
            }
        }
    });
    (pb, progress)
}

/// Cancellation on Ctrl-C is left to the OS default (the process ends; outputs are written
/// atomically, so nothing half-written is left).
pub fn cancel() -> umesh_core::Cancel {
    umesh_core::Cancel::new()
}

/// Print a summary object as one JSON line.
pub fn print_json(value: &serde_json::Value) {
    println!("{}", serde_json::to_string(value).unwrap_or_else(|_| "{}".into()));
}
