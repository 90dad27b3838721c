//! The image layers of a training example, described once (paper appendix A): which layers
//! there are, at which resolution, with how many channels and in which value range. The
//! example, its batch on the host and on a device, and the example cache's records are all
//! [`Layers`] of something, so a new layer is added here and in the code that computes it.
//!
//! | layer | channels | resolution | values | seen by |
//! |---|---|---|---|---|
//! | `photo` | 3 | output | sRGB over the background | D_P |
//! | `relit` | 3 | output | sRGB over the background | D_S |
//! | `albedo_hi` | 3 | output | linear, over the background's albedo | D_A (high) |
//! | `diffuse` | 3 | output | linear HDR times the mask | D_S |
//! | `specular` | 3 | output | linear HDR times the mask | D_S |
//! | `mask` | 1 | output | coverage in [0, 1] | (compositing) |
//! | `albedo_lo` | 3 | volume | area average of `albedo_hi` | D_A (low) |
//! | `normals_lo` | 3 | volume | camera space times the mask, area-averaged | D_G |
//!
//! On the host a layer is row-major with its channels interleaved per pixel; a batch stores
//! it planar (`[batch, channels, side, side]`), with sRGB layers mapped to `[-1, 1]`.

/// One image layer of a training example.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Layer {
    Photo,
    Relit,
    AlbedoHi,
    Diffuse,
    Specular,
    Mask,
    AlbedoLo,
    NormalsLo,
}

/// The resolution a layer is stored at.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Scale {
    /// The output (high) resolution, `side x side`.
    Output,
    /// The volume (low) resolution, `side / factor` per side.
    Volume,
}

impl Layer {
    /// Every layer, in the order of the example cache's records (its format depends on it).
    pub const ALL: [Layer; 8] = [
        Layer::Photo,
        Layer::Relit,
        Layer::AlbedoHi,
        Layer::Diffuse,
        Layer::Specular,
        Layer::Mask,
        Layer::AlbedoLo,
        Layer::NormalsLo,
    ];

    /// The layer's name (its field in [`Layers`]).
    pub const fn name(self) -> &'static str {
        match self {
            Layer::Photo => "photo",
            Layer::Relit => "relit",
            Layer::AlbedoHi => "albedo_hi",
            Layer::Diffuse => "diffuse",
            Layer::Specular => "specular",
            Layer::Mask => "mask",
            Layer::AlbedoLo => "albedo_lo",
            Layer::NormalsLo => "normals_lo",
        }
    }

    /// Values per pixel.
    pub const fn channels(self) -> usize {
        match self {
            Layer::Mask => 1,
            _ => 3,
        }
    }

    /// The resolution it is stored at.
    pub const fn scale(self) -> Scale {
        match self {
            Layer::AlbedoLo | Layer::NormalsLo => Scale::Volume,
            _ => Scale::Output,
        }
    }

    /// Whether the values are sRGB in `[0, 1]`, which a batch maps to `[-1, 1]` (the range of
    /// the generator's relit image); the other layers are batched as they are.
    pub const fn is_srgb(self) -> bool {
        matches!(self, Layer::Photo | Layer::Relit)
    }

    /// Pixels per side for examples of output side `side` and low-resolution `factor`.
    pub const fn side(self, side: usize, factor: usize) -> usize {
        match self.scale() {
            Scale::Output => side,
            Scale::Volume => side / factor,
        }
    }

    /// Values of the layer in one example (`channels x side x side`).
    pub const fn floats(self, side: usize, factor: usize) -> usize {
        let s = self.side(side, factor);
        self.channels() * s * s
    }
}

/// One value per [`Layer`]: an example's pixels, a batch's planes, a batch's tensors, a count.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Layers<T> {
    pub photo: T,
    pub relit: T,
    pub albedo_hi: T,
    pub diffuse: T,
    pub specular: T,
    pub mask: T,
    pub albedo_lo: T,
    pub normals_lo: T,
}

impl<T> Layers<T> {
    /// `f` of every layer, called in the order of [`Layer::ALL`].
    pub fn from_fn(mut f: impl FnMut(Layer) -> T) -> Layers<T> {
        // Struct fields are evaluated in the order written: keep it that of `Layer::ALL`.
        Layers {
            photo: f(Layer::Photo),
            relit: f(Layer::Relit),
            albedo_hi: f(Layer::AlbedoHi),
            diffuse: f(Layer::Diffuse),
            specular: f(Layer::Specular),
            mask: f(Layer::Mask),
            albedo_lo: f(Layer::AlbedoLo),
            normals_lo: f(Layer::NormalsLo),
        }
    }

    /// The value of `layer`.
    pub fn get(&self, layer: Layer) -> &T {
        match layer {
            Layer::Photo => &self.photo,
            Layer::Relit => &self.relit,
            Layer::AlbedoHi => &self.albedo_hi,
            Layer::Diffuse => &self.diffuse,
            Layer::Specular => &self.specular,
            Layer::Mask => &self.mask,
            Layer::AlbedoLo => &self.albedo_lo,
            Layer::NormalsLo => &self.normals_lo,
        }
    }

    /// `f` of every layer's value, by reference.
    pub fn map<U>(&self, mut f: impl FnMut(Layer, &T) -> U) -> Layers<U> {
        Layers::from_fn(|layer| f(layer, self.get(layer)))
    }

    /// Every layer with its value, in the order of [`Layer::ALL`].
    pub fn iter(&self) -> impl Iterator<Item = (Layer, &T)> {
        Layer::ALL
            .into_iter()
            .map(move |layer| (layer, self.get(layer)))
    }
}

/// The pixels of a three-channel layer as RGB triples (a view, no copy).
pub fn rgb(values: &[f32]) -> &[[f32; 3]] {
    let (pixels, rest) = values.as_chunks::<3>();
    assert!(rest.is_empty(), "a three-channel layer holds whole pixels");
    pixels
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_layer_has_one_field_and_the_cache_order_is_fixed() {
        let names = Layers::from_fn(Layer::name);
        for (layer, name) in names.iter() {
            assert_eq!(*name, layer.name());
        }
        // The example cache's format (version 1) stores the layers in this order.
        let order: Vec<&str> = Layer::ALL.iter().map(|l| l.name()).collect();
        assert_eq!(
            order,
            [
                "photo",
                "relit",
                "albedo_hi",
                "diffuse",
                "specular",
                "mask",
                "albedo_lo",
                "normals_lo"
            ]
        );
        let mut calls = Vec::new();
        let _ = Layers::from_fn(|l| calls.push(l));
        assert_eq!(calls, Layer::ALL);
    }

    #[test]
    fn sizes_follow_the_scale_and_channels() {
        assert_eq!(Layer::Photo.floats(64, 2), 3 * 64 * 64);
        assert_eq!(Layer::Mask.floats(64, 2), 64 * 64);
        assert_eq!(Layer::NormalsLo.floats(64, 2), 3 * 32 * 32);
        let total: usize = Layer::ALL.iter().map(|l| l.floats(64, 2)).sum();
        // Five RGB layers and the mask at 64^2, two RGB layers at 32^2.
        assert_eq!(total, 16 * 64 * 64 + 6 * 32 * 32);
        let counts = Layers::from_fn(|l| l.channels());
        assert_eq!(counts.mask, 1);
        assert_eq!(counts.map(|_, c| c * 2).relit, 6);
        assert_eq!(
            rgb(&[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]),
            &[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]
        );
    }
}
