//! umesh: physics-based deep network for augmented reality in liver surgery.
//! The binary is a thin shell: commands live in `cli/`, the desktop app in `app/`.

fn main() -> std::process::ExitCode {
    umesh::cli::main()
}
