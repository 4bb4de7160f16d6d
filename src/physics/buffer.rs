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
}
