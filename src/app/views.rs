//! The app's views, in the order of their tabs: the one list the shell iterates (as rerun's
//! `default_views.rs`). A new view is a folder with a `view.rs` implementing `View`, and a
//! line here.

use crate::app::shell::views::RegisterView;
use bevy::prelude::*;

pub fn register_default_views(app: &mut App) {
    app.register_view::<crate::app::model::view::ModelView>()
        .register_view::<crate::app::jobs::view::JobsView>()
        .register_view::<crate::app::qa::view::QaView>()
        .register_view::<crate::app::ar::view::ArView>();
}
