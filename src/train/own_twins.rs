//! The network's own twins (ours, [`OwnTwins`]): the poses the network now confuses with the
//! truth, found in its answers on fresh crops, for twin sampling to draw negatives around
//! (`docs/DESIGN.md` §2, "Sampling").
//!
//! Half of the realistic misses of the drill and the duplo were measured to be half-turns
//! (`examples/probe_twins`), and for the duplo no near-symmetry of its geometry records the turn
//! (the upside-down brick), so the twins are read from the network rather than from the part.

use nalgebra::Rotation3;

use super::TrainError;
use super::data::FreshRenders;
use super::sampling::OwnTwins;
use crate::net::{Network, NetworkConfig, ProjectedGrid};
use crate::so3::metrics::HALF_TURN_DEG;

/// The level of the grid whose argmax is compared with the truth (4 608 cells, about 15° apart:
/// fine enough to tell a half-turn, cheap enough to run every few hundred steps).
pub const OWN_TWINS_LEVEL: u8 = 2;

/// Per object, the turns `D = R_t⁻¹·R̂` (object frame, [`half_turn_miss`]) of the network's
/// half-turn misses (argmax `R̂`) on `own.crops` fresh crops of it drawn from
/// `seed`: realistic crops made as the training crops are (`fresh`'s own scene assets) when
/// `fresh` renders realistic ones, else flat renders; `symmetries[i]` are object `i`'s proper symmetries (none: the identity alone).
/// `network` is the plain (non-autodiff) network, its BatchNorm statistics synced.
pub fn own_twins(
    network: &Network,
    config: &NetworkConfig,
    fresh: &FreshRenders,
    symmetries: &[Vec<Rotation3<f64>>],
    own: OwnTwins,
    seed: u64,
) -> Result<Vec<Vec<Rotation3<f64>>>, TrainError> {
    let size = config.image_size;
    let crops: Vec<(usize, Vec<u8>, Rotation3<f64>)> = match &fresh.realism {
        Some(assets) => fresh
            .realistic_crops_of(assets, size, own.crops, seed)
            .into_iter()
            .map(|(i, c)| (i, c.rgb, c.r_virtual))
            .collect(),
        None => fresh
            .eval_crops(size, own.crops, seed)
            .into_iter()
            .map(|(i, c)| (i, c.rgb, c.r_virtual))
            .collect(),
    };
    let projected = ProjectedGrid::new(network, config, OWN_TWINS_LEVEL)
        .map_err(|e| TrainError::Data(format!("the own twins' grid: {e}")))?;
    let rgb: Vec<&[u8]> = crops.iter().map(|(_, c, _)| c.as_slice()).collect();
    let guesses = projected.argmax_of_crops(network, &rgb, size as usize);
    let mut twins = vec![Vec::new(); fresh.meshes.len()];
    for ((object, _, r_gt), guess) in crops.iter().zip(guesses) {
        let group = symmetries.get(*object).map_or(&[][..], |g| g.as_slice());
        if let Some(turn) = half_turn_miss(&guess, r_gt, group) {
            twins[*object].push(turn);
        }
    }
    Ok(twins)
}

/// The turn `r_gt⁻¹·guess` (object frame) when `guess` is at least [`HALF_TURN_DEG`] from every
/// equivalent truth `r_gt·S` (`S` in `group`; the identity alone when `group` is empty); `None`
/// otherwise. The turn is taken from `r_gt` itself, not from the nearest equivalent: twin sampling
/// draws around `R_gt·D`, and the scores and targets are the same on every equivalent of a pose.
pub fn half_turn_miss(
    guess: &Rotation3<f64>,
    r_gt: &Rotation3<f64>,
    group: &[Rotation3<f64>],
) -> Option<Rotation3<f64>> {
    let identity = [Rotation3::identity()];
    let group = if group.is_empty() {
        &identity[..]
    } else {
        group
    };
    let nearest = group
        .iter()
        .map(|s| ((r_gt * s).inverse() * guess).angle())
        .fold(f64::INFINITY, f64::min);
    (nearest.to_degrees() >= HALF_TURN_DEG).then(|| r_gt.inverse() * guess)
}

#[cfg(test)]
mod tests {
    use super::half_turn_miss;
    use crate::so3::{rot_x, rot_z};
    use nalgebra::Rotation3;
    use std::f64::consts::PI;

    #[test]
    fn a_half_turn_miss_is_far_from_every_equivalent_and_turns_from_the_truth_itself() {
        let r_gt = rot_z(0.3) * rot_x(1.1);
        let flip = rot_x(PI);
        // No symmetry: the flip is a miss, and its turn is the flip.
        let turn = half_turn_miss(&(r_gt * flip), &r_gt, &[]).expect("a half-turn miss");
        assert!((turn.inverse() * flip).angle() < 1e-9);
        // 140° is not a half-turn.
        assert!(half_turn_miss(&(r_gt * rot_x(140f64.to_radians())), &r_gt, &[]).is_none());
        // Under C2 about x the flip is the truth's equivalent: no miss.
        let c2 = [Rotation3::identity(), rot_x(PI)];
        assert!(half_turn_miss(&(r_gt * flip), &r_gt, &c2).is_none());
        // Under C2 about z, a flip about x is 180° from both equivalents.
        let c2z = [Rotation3::identity(), rot_z(PI)];
        let turn = half_turn_miss(&(r_gt * flip), &r_gt, &c2z).expect("a miss under C2 about z");
        assert!((turn.inverse() * flip).angle() < 1e-9);
    }
}
