//! A plain row-major image buffer shared by the physics and the I/O layers.

/// A row-major single-channel image: `data[row * width + col]`.
#[derive(Debug, Clone, PartialEq)]
pub struct ImageBuf<T> {
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// Row-major samples, `width * height` of them.
    pub data: Vec<T>,
}

impl<T: Clone> ImageBuf<T> {
    /// An image filled with one value.
    pub fn filled(width: usize, height: usize, value: T) -> Self {
        Self {
            width,
            height,
            data: vec![value; width * height],
        }
    }
}

impl<T> ImageBuf<T> {
    /// Wraps samples; `None` when their count is not `width * height`.
    pub fn from_vec(width: usize, height: usize, data: Vec<T>) -> Option<Self> {
        (data.len() == width * height).then_some(Self { width, height, data })
    }

    /// Number of pixels.
    pub fn len(&self) -> usize {
        self.data.len()
    }

    /// True when the image has no pixels.
    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }

    /// Sample at column `col`, row `row`.
    pub fn at(&self, col: usize, row: usize) -> &T {
        &self.data[row * self.width + col]
    }

    /// Same size as another image.
    pub fn same_size<U>(&self, other: &ImageBuf<U>) -> bool {
        self.width == other.width && self.height == other.height
    }
}

/// Values at some of an image's pixels: the values in pixel order and each
/// pixel's place among them (4 bytes a pixel, where an `ImageBuf<Option<T>>`
/// writes a whole `T` at every pixel). What a frame knows at its segmented
/// pixels, often a small part of the image.
#[derive(Debug, Clone, PartialEq)]
pub struct SparseImage<T> {
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// Per pixel, its value's index in `values` ([`SparseImage::NONE`] for none).
    slot: Vec<u32>,
    /// The pixels holding a value, ascending, and their values.
    pixels: Vec<u32>,
    values: Vec<T>,
}

impl<T> SparseImage<T> {
    /// The slot of a pixel without a value.
    const NONE: u32 = u32::MAX;

    /// An image holding no value; `None` when it has `u32::MAX` pixels or more.
    pub fn empty(width: usize, height: usize) -> Option<Self> {
        let n = width.checked_mul(height)?;
        (n < Self::NONE as usize).then(|| Self {
            width,
            height,
            slot: vec![Self::NONE; n],
            pixels: vec![],
            values: vec![],
        })
    }

    /// The values `f` gives at the pixels where `mask` holds (it may give
    /// none); `None` when the image has `u32::MAX` pixels or more.
    pub fn from_mask(mask: &ImageBuf<bool>, mut f: impl FnMut(usize) -> Option<T>) -> Option<Self> {
        let mut out = Self::empty(mask.width, mask.height)?;
        let expected = mask.data.iter().filter(|&&m| m).count();
        out.pixels.reserve_exact(expected);
        out.values.reserve_exact(expected);
        for (i, _) in mask.data.iter().enumerate().filter(|&(_, &m)| m) {
            if let Some(v) = f(i) {
                out.pixels.push(i as u32);
                out.values.push(v);
            }
        }
        // The slots afterwards, in a loop of their own.
        for (k, &p) in out.pixels.iter().enumerate() {
            out.slot[p as usize] = k as u32;
        }
        Some(out)
    }

    /// The values `values` at the pixels `pixels` (ascending, one value each); `None` when
    /// the image has `u32::MAX` pixels or more, or the pixels are not ascending within it.
    pub fn from_pixels(width: usize, height: usize, pixels: Vec<u32>, values: Vec<T>) -> Option<Self> {
        let mut out = Self::empty(width, height)?;
        let ascending = pixels.windows(2).all(|p| p[0] < p[1]);
        let inside = pixels.last().is_none_or(|&p| (p as usize) < out.slot.len());
        if pixels.len() != values.len() || !ascending || !inside {
            return None;
        }
        for (k, &p) in pixels.iter().enumerate() {
            out.slot[p as usize] = k as u32;
        }
        (out.pixels, out.values) = (pixels, values);
        Some(out)
    }

    /// The value at pixel `i`, if any.
    #[inline]
    pub fn get(&self, i: usize) -> Option<&T> {
        let s = *self.slot.get(i)?;
        self.values.get(s as usize)
    }

    /// The pixels holding a value and their values, in pixel order.
    pub fn iter(&self) -> impl Iterator<Item = (usize, &T)> + '_ {
        self.pixels.iter().map(|&p| p as usize).zip(&self.values)
    }

    /// Pixels holding a value.
    pub fn count(&self) -> usize {
        self.values.len()
    }

    /// The values, in pixel order (those of [`SparseImage::pixels`]).
    pub fn values(&self) -> &[T] {
        &self.values
    }

    /// The pixels holding a value, ascending.
    pub fn pixels(&self) -> impl ExactSizeIterator<Item = usize> + '_ {
        self.pixels.iter().map(|&p| p as usize)
    }
}

/// A rectangle of an image `full_width` wide: columns from `col0`, rows from
/// `row0`, `width` by `height`. Work on a small object in a large image is
/// done on the rectangle around it, not the whole image.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Region {
    /// First column.
    pub col0: usize,
    /// First row.
    pub row0: usize,
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// Columns of the image it is a part of.
    pub full_width: usize,
}

impl Region {
    /// The smallest rectangle holding every pixel where `mask` holds, grown to
    /// the grid of `align x align` blocks from the image's corner (its edges on
    /// multiples of `align`, or the image's edge), so blocks of that side are
    /// the same blocks in the rectangle as in the image. `None` for an empty mask.
    pub fn around(mask: &ImageBuf<bool>, align: usize) -> Option<Self> {
        let (w, h) = (mask.width, mask.height);
        let (mut c0, mut c1, mut r0, mut r1) = (usize::MAX, 0, usize::MAX, 0);
        for (r, row) in mask.data.chunks_exact(w.max(1)).enumerate().take(h) {
            let Some(first) = row.iter().position(|&m| m) else {
                continue;
            };
            let last = row.iter().rposition(|&m| m).unwrap_or(first);
            (c0, c1) = (c0.min(first), c1.max(last + 1));
            (r0, r1) = (r0.min(r), r + 1);
        }
        if c0 == usize::MAX {
            return None;
        }
        let a = align.max(1);
        let (c0, r0) = (c0 / a * a, r0 / a * a);
        let (c1, r1) = ((c1.div_ceil(a) * a).min(w), (r1.div_ceil(a) * a).min(h));
        Some(Self {
            col0: c0,
            row0: r0,
            width: c1 - c0,
            height: r1 - r0,
            full_width: w,
        })
    }

    /// Pixels in the rectangle.
    pub fn len(&self) -> usize {
        self.width * self.height
    }

    /// True when the rectangle has no pixels.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Every pixel of the rectangle as `(its index in the rectangle, its index
    /// in the image)`, row-major.
    pub fn pixels(&self) -> impl Iterator<Item = (usize, usize)> + '_ {
        (0..self.height).flat_map(move |r| {
            let (local, full) = (r * self.width, (self.row0 + r) * self.full_width + self.col0);
            (0..self.width).map(move |c| (local + c, full + c))
        })
    }

    /// The rectangle's part of `image` (which must be `full_width` wide and hold it).
    pub fn crop<T: Clone>(&self, image: &ImageBuf<T>) -> ImageBuf<T> {
        let mut data = Vec::with_capacity(self.len());
        for r in self.row0..self.row0 + self.height {
            let start = r * image.width + self.col0;
            data.extend_from_slice(&image.data[start..start + self.width]);
        }
        ImageBuf {
            width: self.width,
            height: self.height,
            data,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn region_holds_the_mask_on_the_block_grid() {
        let mut mask = ImageBuf::filled(10, 8, false);
        for (c, r) in [(4, 2), (6, 5), (5, 3)] {
            mask.data[r * 10 + c] = true;
        }
        let region = Region::around(&mask, 3).unwrap();
        // Columns 4..7 grow to 3..9, rows 2..6 to 0..6.
        assert_eq!((region.col0, region.width, region.row0, region.height), (3, 6, 0, 6));
        let cropped = region.crop(&mask);
        let pairs: Vec<(usize, usize)> = region.pixels().filter(|&(i, _)| cropped.data[i]).collect();
        assert_eq!(pairs, vec![(13, 24), (20, 35), (33, 56)]);
        // Every pixel, in order, and each the image's own.
        assert_eq!(region.pixels().count(), region.len());
        assert!(region.pixels().all(|(i, f)| cropped.data[i] == mask.data[f]));
        assert!(region.pixels().enumerate().all(|(k, (i, _))| k == i));
        // At the image's edge the rectangle stops there, off the grid.
        mask.data[7 * 10 + 9] = true;
        let region = Region::around(&mask, 3).unwrap();
        assert_eq!((region.col0, region.width, region.row0, region.height), (3, 7, 0, 8));
        assert!(Region::around(&ImageBuf::filled(4, 4, false), 3).is_none());
    }

    #[test]
    fn sparse_image_holds_what_it_was_given_where_it_was_given() {
        let (w, h) = (7, 5);
        let dense: Vec<Option<f64>> = (0..w * h)
            .map(|i| (i % 3 == 1 && i % 4 != 0).then_some(i as f64 * 0.5))
            .collect();
        let mask = ImageBuf::from_vec(w, h, (0..w * h).map(|i| i % 2 == 1).collect()).unwrap();
        let s = SparseImage::from_mask(&mask, |i| dense[i]).unwrap();
        for (i, d) in dense.iter().enumerate() {
            let want = if i % 2 == 1 { *d } else { None };
            assert_eq!(s.get(i).copied(), want, "pixel {i}");
        }
        assert_eq!(s.get(w * h), None);
        let held: Vec<(usize, f64)> = s.iter().map(|(i, v)| (i, *v)).collect();
        let want: Vec<(usize, f64)> = (0..w * h)
            .filter(|&i| mask.data[i])
            .filter_map(|i| dense[i].map(|v| (i, v)))
            .collect();
        assert_eq!(held, want);
        assert_eq!(s.count(), want.len());
        let (pixels, values): (Vec<usize>, Vec<f64>) = want.iter().copied().unzip();
        assert_eq!(s.pixels().collect::<Vec<_>>(), pixels);
        assert_eq!(s.values(), values);
        assert!(SparseImage::<u8>::empty(1 << 16, 1 << 16).is_none());
        // The same image from its pixels and values; pixels out of order or outside refused.
        let again = SparseImage::from_pixels(w, h, s.pixels.clone(), s.values.clone()).unwrap();
        assert_eq!(again, s);
        assert!(SparseImage::from_pixels(w, h, vec![3, 1], vec![0.0, 1.0]).is_none());
        assert!(SparseImage::from_pixels(w, h, vec![1, 1], vec![0.0, 1.0]).is_none());
        assert!(SparseImage::from_pixels(w, h, vec![(w * h) as u32], vec![0.0]).is_none());
        assert!(SparseImage::from_pixels(w, h, vec![1], vec![0.0, 1.0]).is_none());
    }
}
