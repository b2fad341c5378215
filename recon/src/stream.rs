//! Pulling rows from a [`BucketSource`] with the checks every method needs.

use super::{BucketBlock, BucketSource, Control, ReconError};

/// Wraps a source: checks that blocks arrive in order, hold whole rows (`rows x channels`) of
/// finite values and do not run past `total`; turns a short source into [`ReconError::Unsolvable`] and a raised
/// cancellation flag into [`ReconError::Cancelled`].
pub(crate) struct RowStream<'s, 'c> {
    source: &'s mut dyn BucketSource,
    control: &'c Control,
    channels: usize,
    total: u64,
    next: u64,
}

impl<'s, 'c> RowStream<'s, 'c> {
    pub(crate) fn new(
        source: &'s mut dyn BucketSource,
        control: &'c Control,
        channels: usize,
        total: u64,
    ) -> Result<Self, ReconError> {
        if channels == 0 {
            return Err(ReconError::BadRows(
                "a problem needs at least one channel".into(),
            ));
        }
        if total == 0 {
            return Err(ReconError::Unsolvable("no rows to reconstruct from".into()));
        }
        Ok(RowStream {
            source,
            control,
            channels,
            total,
            next: 0,
        })
    }

    /// The next checked block (`values.len()` a multiple of `channels`, `first_row` the next
    /// expected row), or `None` once the source is exhausted with all `total` rows delivered.
    pub(crate) fn next_block(&mut self) -> Result<Option<BucketBlock>, ReconError> {
        if self.control.is_cancelled() {
            return Err(ReconError::Cancelled);
        }
        let Some(block) = self.source.next_block()? else {
            if self.next < self.total {
                return Err(ReconError::Unsolvable(format!(
                    "the source ended after {} of {} rows",
                    self.next, self.total
                )));
            }
            return Ok(None);
        };
        if block.values.len() % self.channels != 0 {
            return Err(ReconError::BadRows(format!(
                "block at row {} holds {} values, not a multiple of {} channels",
                block.first_row,
                block.values.len(),
                self.channels
            )));
        }
        if block.first_row != self.next {
            return Err(ReconError::BadRows(format!(
                "block starts at row {}, expected row {}",
                block.first_row, self.next
            )));
        }
        if let Some(i) = block.values.iter().position(|v| !v.is_finite()) {
            return Err(ReconError::BadRows(format!(
                "non-finite bucket value {} at row {} channel {}",
                block.values[i],
                block.first_row + (i / self.channels) as u64,
                i % self.channels
            )));
        }
        let rows = (block.values.len() / self.channels) as u64;
        if self.next + rows > self.total {
            return Err(ReconError::BadRows(format!(
                "block rows {}..{} run past the {} rows of the problem",
                self.next,
                self.next + rows,
                self.total
            )));
        }
        self.next += rows;
        Ok(Some(block))
    }

    /// Rows delivered so far.
    pub(crate) fn rows_seen(&self) -> u64 {
        self.next
    }

    pub(crate) fn total(&self) -> u64 {
        self.total
    }
}
