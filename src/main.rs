//! umesh: physics-based deep network for augmented reality in liver surgery.
//! The binary is a thin shell: each command lives in `cli/`.

mod cli;

fn main() -> std::process::ExitCode {
    cli::main()
}
