//! The error of a value, setting or input that is out of range or malformed, shared by the
//! checks of every module (settings' `validate`, parsers of names and files); a module's own
//! error enum wraps it with its context.

/// What is wrong and with which value; the message names it.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct Invalid(pub String);

impl From<String> for Invalid {
    fn from(message: String) -> Self {
        Self(message)
    }
}

impl From<&str> for Invalid {
    fn from(message: &str) -> Self {
        Self(message.to_string())
    }
}

/// A job stopped because its `Cancel` flag was set: one type, which every error enum of the
/// libraries wraps (`From`), so `cancel.check()?` works in any of them.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
#[error("cancelled")]
pub struct Cancelled;

/// A model that failed to predict a frame (the network's error, or the FE fit's), its source kept.
pub type ModelError = Box<dyn std::error::Error + Send + Sync>;

/// Where an error type carries its reason as text (a path and why), the reason is the message.
impl From<Invalid> for String {
    fn from(e: Invalid) -> Self {
        e.0
    }
}
