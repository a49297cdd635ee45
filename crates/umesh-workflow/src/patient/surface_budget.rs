//! The organ surface a registration frame can afford: the surface is judged against the
//! observed points and drawn every frame, so a large organ voxelised finely (a mesh at 1 mm)
//! is marched at a coarser step until it has at most `PrepareSettings::max_surface_triangles`.

use super::folder::PrepareSettings;
use umesh_core::dataset::organ_surface;
use umesh_core::segmentation::Segmentation;
use umesh_core::{Cancel, Cancelled};

/// Steps beyond this are not tried (the dataset refuses more: a liver is then a handful of
/// triangles).
const MAX_SURFACE_STEP: usize = 16;

/// `settings` with the surface step a frame affords: as asked when the organ's surface has at
/// most `max_surface_triangles` triangles (or the limit is 0), else the smallest larger step
/// whose surface fits; `surface_description` says which and why.
pub fn fit_surface_to_budget(
    seg: &Segmentation,
    settings: &PrepareSettings,
    cancel: &Cancel,
) -> Result<PrepareSettings, Cancelled> {
    let mask = seg.organ_mask();
    let triangles = |step: usize| organ_surface(&mask, step).triangles.len();
    let asked = settings.dataset.surface_step;
    let first = triangles(asked);
    let limit = settings.max_surface_triangles;
    let mut out = settings.clone();
    if limit == 0 || first <= limit {
        out.surface_description = format!("marched every {asked} voxels: {first} triangles");
        return Ok(out);
    }
    let (mut step, mut n) = (asked, first);
    while n > limit && step < MAX_SURFACE_STEP {
        cancel.check()?;
        step += 1;
        n = triangles(step);
    }
    out.dataset.surface_step = step;
    out.surface_description = format!(
        "marched every {step} voxels: {n} triangles (every {asked} voxels it had {first}, over the {limit} a registration frame judges and draws in time; --max-surface-triangles 0 keeps the step)"
    );
    Ok(out)
}
