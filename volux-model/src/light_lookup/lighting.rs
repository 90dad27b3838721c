//! The lighting a render is shaded with: one light map per Phong exponent for every batch
//! element, and each element's environment yaw, checked ([`Lighting`]), and how light-map sets
//! become one ([`lighting_tensors`]). The look-up itself is [`super::LightMapBatch`].

use burn::tensor::{Device, Tensor, TensorData};
use volux_envmap::{LightMap, LightMapSet};

use super::{LightLookupError, LightMapBatch};

/// Light maps for shading: `maps[i]` holds exponent `n_i` for every batch element, the first
/// must be `n = 1` (it also gives `D`), and `yaw` rotates each element's environment.
#[derive(Clone, Debug)]
pub struct Lighting {
    pub maps: Vec<LightMapBatch>,
    /// `[batch]` radians, or `None`.
    pub yaw: Option<Tensor<1>>,
}

/// Why lighting cannot be used.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum LightingError {
    #[error("lighting needs at least one light map")]
    NoMaps,
    #[error(
        "the first light map must have Phong exponent 1 (it gives the diffuse shading), got {0}"
    )]
    FirstNotDiffuse(u32),
    #[error("light map {index} (n={exponent}) has batch {batch}, map 0 has {batch0}")]
    BatchMismatch {
        index: usize,
        exponent: u32,
        batch: usize,
        batch0: usize,
    },
}

impl Lighting {
    /// Checks that the first map is `n = 1` and that all share one batch size.
    pub fn new(maps: Vec<LightMapBatch>, yaw: Option<Tensor<1>>) -> Result<Self, LightingError> {
        let first = maps.first().ok_or(LightingError::NoMaps)?;
        if first.exponent() != 1 {
            return Err(LightingError::FirstNotDiffuse(first.exponent()));
        }
        for (index, m) in maps.iter().enumerate() {
            if m.batch() != first.batch() {
                return Err(LightingError::BatchMismatch {
                    index,
                    exponent: m.exponent(),
                    batch: m.batch(),
                    batch0: first.batch(),
                });
            }
        }
        Ok(Self { maps, yaw })
    }
}

/// Why light-map sets cannot be put on a device as a [`Lighting`].
#[derive(Debug, thiserror::Error)]
pub enum LightingTensorError {
    #[error("draw names environment {0} of a bank of {1}")]
    Index(usize, usize),
    #[error("an environment lacks the light map of exponent {0}")]
    Exponent(u32),
    #[error(transparent)]
    Maps(#[from] LightLookupError),
    #[error(transparent)]
    Lighting(#[from] LightingError),
}

/// The generator's [`Lighting`] for one light-map set and environment yaw per batch element
/// (the sets' exponents, in their order, are the maps').
pub fn lighting_tensors(
    sets: &[&LightMapSet],
    yaws: &[f64],
    device: &Device,
) -> Result<Lighting, LightingTensorError> {
    assert_eq!(sets.len(), yaws.len(), "one yaw per light-map set");
    let exponents = sets
        .first()
        .ok_or(LightingTensorError::Index(0, 0))?
        .exponents();
    let mut maps = Vec::with_capacity(exponents.len());
    for n in exponents {
        let per_example: Vec<&LightMap> = sets
            .iter()
            .map(|s| s.get(n).ok_or(LightingTensorError::Exponent(n)))
            .collect::<Result<_, _>>()?;
        maps.push(LightMapBatch::new(&per_example, device)?);
    }
    let yaw: Vec<f32> = yaws.iter().map(|&y| y as f32).collect();
    let yaw = Tensor::<1>::from_data(TensorData::new(yaw, [yaws.len()]), device);
    Ok(Lighting::new(maps, Some(yaw))?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_support::wave_light_maps as light_maps;

    #[test]
    fn lighting_is_checked() {
        let device = Device::flex();
        let maps = light_maps(1, 1.0);
        let spec_only = LightMapBatch::new(&[&maps[1]], &device).unwrap();
        assert_eq!(
            Lighting::new(vec![spec_only], None).unwrap_err(),
            LightingError::FirstNotDiffuse(16)
        );
        assert_eq!(
            Lighting::new(vec![], None).unwrap_err(),
            LightingError::NoMaps
        );
        let one = LightMapBatch::new(&[&maps[0]], &device).unwrap();
        let two = LightMapBatch::new(&[&maps[1], &maps[1]], &device).unwrap();
        assert!(matches!(
            Lighting::new(vec![one, two], None),
            Err(LightingError::BatchMismatch { index: 1, .. })
        ));
    }
}
