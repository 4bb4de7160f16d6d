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
