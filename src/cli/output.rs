//! How commands report: a progress bar on stderr, cancellation, one JSON line on stdout.

/// A progress bar on stderr fed by core's progress callback; hidden when stderr is not a
/// terminal-like sink (indicatif handles that).
pub fn progress_bar(message: &str) -> (indicatif::ProgressBar, umesh_core::Progress) {
    let pb = indicatif::ProgressBar::new(0);
    pb.set_style(
        indicatif::ProgressStyle::with_template("{spinner} {msg} [{bar:30}] {pos}/{len} ({elapsed}, eta {eta})")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    pb.set_message(message.to_string());
    let p = pb.clone();
    let progress = umesh_core::Progress::new(move |done, total, msg| {
        if total > 0 {
            p.set_length(total);
        }
        p.set_position(done);
        if !msg.is_empty() {
            p.set_message(msg.to_string());
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
