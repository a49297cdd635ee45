//! The views the shell shows, registered in one list (`app/views.rs`), as rerun's viewer
//! registers its view classes: each view says what the shell needs of it (its tab, whether
//! the 3-D view shows, its keys for the help window) and hands over its systems: the panels
//! (given the window's root `Ui`, they take what they need and leave the rest to the 3-D
//! view), the keyboard shortcuts and the colour scale. The shell knows no view's resources.

use crate::app::state::Mode;
use bevy::ecs::system::SystemId;
use bevy::prelude::*;
use bevy_egui::egui;

/// The panels of a view: run with the window's root `Ui` while the view is active.
pub type PanelsSystem = SystemId<InMut<'static, egui::Ui>>;
/// What the colour scale in the 3-D view's corner shows: its top (mm) and what it measures.
pub type ScaleSystem = SystemId<(), Option<(f64, String)>>;

#[derive(Clone)]
pub struct ViewEntry {
    pub mode: Mode,
    /// The tab's name in the menu bar.
    pub name: &'static str,
    /// Whether the 3-D view fills what the panels leave (the jobs and AR views are pure UI).
    pub shows_3d: bool,
    /// (key, what it does) for the help window, while this view is active.
    pub keys: &'static [(&'static str, &'static str)],
    pub panels: PanelsSystem,
    /// Run before the panels when egui does not want the keyboard.
    pub shortcuts: Option<SystemId>,
    pub scale: Option<ScaleSystem>,
}

/// A view of the app: registers its systems and says what the shell needs of it.
pub trait View {
    fn entry(world: &mut World) -> ViewEntry;
}

/// The registered views, in the order of their tabs.
#[derive(Resource, Default)]
pub struct ViewRegistry(Vec<ViewEntry>);

impl ViewRegistry {
    pub fn get(&self, mode: Mode) -> Option<&ViewEntry> {
        self.0.iter().find(|v| v.mode == mode)
    }

    pub fn iter(&self) -> impl Iterator<Item = &ViewEntry> {
        self.0.iter()
    }
}

pub trait RegisterView {
    fn register_view<V: View>(&mut self) -> &mut Self;
}

impl RegisterView for App {
    fn register_view<V: View>(&mut self) -> &mut Self {
        let entry = V::entry(self.world_mut());
        self.world_mut().get_resource_or_init::<ViewRegistry>().0.push(entry);
        self
    }
}
