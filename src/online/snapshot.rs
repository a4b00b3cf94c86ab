//! Arrays whose copy costs one pointer per chunk: what a renewal's builder takes of the live
//! system at its start.
//!
//! A renewal (module `laplacian`) builds a factor beside the live one from a snapshot of the
//! rows `(a, b, √w, y)`, the anchors' priors and every row's tail and translation (for its
//! re-linearisation), as they are at its start. Flat copies of those arrays cost O(edges) on
//! the robot's thread, in the step that starts the renewal, much of it first touches of fresh
//! memory. Measured with scratch timers around the start (`benches/MEASUREMENTS.md`,
//! forty-first session): 0.19–0.57 ms on city10000 and 2.0–7.1 ms on a 100 000-pose world at
//! its end, against p99 steps of about 0.13 and 2.5 ms. That cost grows with the map.
//!
//! [`Chunked`] keeps an array as full chunks of [`CHUNK`] elements behind reference counts,
//! and the elements after them (the tail) in a vector of its own: element `i` is
//! `full[i / CHUNK][i % CHUNK]`, or in the tail. A copy shares the full chunks and copies the
//! tail (at most a chunk); a write into a shared chunk first copies that chunk alone (copy on
//! write). So a snapshot costs a pointer per chunk and a tail, and each write after it at most
//! one chunk's copy, once. Appending, and writing the newest elements (what a step does), go to
//! the tail and touch no reference count. With it the same starts took 0.03–0.16 ms on
//! city10000 (median 0.06) and 0.02–0.17 ms on the 100 000-pose world.
//!
//! A pass over every element walks the slices ([`Chunked::slices`]), side by side for arrays of
//! one length; over city10000's 20 000 rows such a pass took 109–112 µs against 90–95 over plain
//! vectors (best of five repetitions): the price of the shared chunks, paid by the passes a
//! re-linearisation and a build make, where the start saved a copy of every row.
//!
//! Elements are only appended or removed at the end, and read or written in place: what the
//! rows need. Written by hand: the crates of persistent vectors (`imbl`, `rpds`) are trees with
//! a path per element and no contiguous chunks to walk; this is a list of shared slices.

use std::collections::TryReserveError;
use std::ops::Range;
use std::sync::Arc;

/// Elements per chunk: a chunk's copy on write is `CHUNK` elements (24 KiB of 24-byte rows),
/// a snapshot one pointer per `CHUNK` elements.
pub(crate) const CHUNK: usize = 1024;

/// An array kept as shared chunks (see the module docs): the full chunks behind reference
/// counts, the last (`tail`, fewer than [`CHUNK`] elements, or exactly that many until the next
/// push) a plain vector of its own, so that appending and writing the newest elements — what
/// a step does — touch no reference count.
#[derive(Debug)]
pub(crate) struct Chunked<T> {
    /// Chunk c holds elements `c·CHUNK..(c + 1)·CHUNK`.
    full: Vec<Arc<Vec<T>>>,
    /// The elements after the full chunks.
    tail: Vec<T>,
    /// Empty vectors of a chunk's room, reserved for the tails to come.
    spare: Vec<Vec<T>>,
}

impl<T> Default for Chunked<T> {
    fn default() -> Self {
        Self {
            full: Vec::new(),
            tail: Vec::new(),
            spare: Vec::new(),
        }
    }
}

/// A copy: the full chunks shared, the tail copied (into a chunk's room), no spare room.
impl<T: Copy> Clone for Chunked<T> {
    fn clone(&self) -> Self {
        let mut tail = Vec::with_capacity(CHUNK.max(self.tail.len()));
        tail.extend_from_slice(&self.tail);
        Self {
            full: self.full.clone(),
            tail,
            spare: Vec::new(),
        }
    }
}

impl<T: Copy> Chunked<T> {
    /// Number of elements.
    pub fn len(&self) -> usize {
        self.full.len() * CHUNK + self.tail.len()
    }

    /// Element i.
    pub fn get(&self, i: usize) -> Option<&T> {
        match self.full.get(i / CHUNK) {
            Some(chunk) => chunk.get(i % CHUNK),
            None => self.tail.get(i - self.full.len() * CHUNK),
        }
    }

    /// Append an element.
    pub fn push(&mut self, value: T) {
        if self.tail.len() >= CHUNK {
            let next = self
                .spare
                .pop()
                .unwrap_or_else(|| Vec::with_capacity(CHUNK));
            self.full
                .push(Arc::new(std::mem::replace(&mut self.tail, next)));
        }
        self.tail.push(value);
    }

    /// Remove the last element.
    pub fn pop(&mut self) -> Option<T> {
        if self.tail.is_empty() {
            let last = self.full.pop()?;
            let chunk = Arc::try_unwrap(last).unwrap_or_else(|shared| shared.to_vec());
            let empty = std::mem::replace(&mut self.tail, chunk);
            if empty.capacity() >= CHUNK {
                self.spare.push(empty);
            }
        }
        self.tail.pop()
    }

    /// The elements in order.
    pub fn iter(&self) -> impl Iterator<Item = &T> + Clone + '_ {
        (self.full.iter().flat_map(|c| c.iter())).chain(self.tail.iter())
    }

    /// The elements as slices in order: the full chunks, then the tail. Two arrays of the same
    /// length have the same slices' lengths, so they can be walked side by side a slice at a
    /// time ([`Iterator::zip`] of slices, which the compiler makes one loop).
    pub fn slices(&self) -> impl Iterator<Item = &[T]> + Clone + '_ {
        (self.full.iter().map(|c| c.as_slice())).chain(std::iter::once(self.tail.as_slice()))
    }

    /// The elements `range` as slices in order ([`Self::slices`] cut to the range, chunks
    /// before it skipped): two arrays of the same length give the same slices' lengths here
    /// too.
    pub fn slices_in(&self, range: Range<usize>) -> impl Iterator<Item = &[T]> + Clone + '_ {
        let range = (range.start, range.end);
        (self.slices().enumerate().skip(range.0 / CHUNK))
            .take_while(move |&(c, _)| touches(range, c))
            .map(move |(c, s)| &s[cut(range, c, s.len())])
    }

    /// [`Self::slices_in`] to write: only the chunks the range touches are copied first when
    /// shared.
    pub fn slices_in_mut(&mut self, range: Range<usize>) -> impl Iterator<Item = &mut [T]> + '_ {
        let range = (range.start, range.end);
        let (first, tail_at) = (range.0 / CHUNK, self.full.len());
        let full = (self.full.iter_mut().enumerate().skip(first))
            .take_while(move |&(c, _)| touches(range, c))
            .map(|(c, chunk)| (c, Arc::make_mut(chunk).as_mut_slice()));
        let tail = std::iter::once((tail_at, self.tail.as_mut_slice()));
        let tail = tail.filter(move |&(c, _)| c >= first && touches(range, c));
        full.chain(tail).map(move |(c, s)| {
            let len = s.len();
            &mut s[cut(range, c, len)]
        })
    }

    /// The elements in order, to write (every shared chunk copied first).
    pub fn iter_mut(&mut self) -> impl Iterator<Item = &mut T> + '_ {
        let len = self.len();
        self.slices_in_mut(0..len).flatten()
    }

    /// Room for `additional` more elements: the tail's and spare chunks' allocated ahead, so
    /// that pushes up to there allocate only a chunk's reference count.
    pub fn try_reserve(&mut self, additional: usize) -> Result<(), TryReserveError> {
        let chunks = self.len().saturating_add(additional).div_ceil(CHUNK);
        (self.full).try_reserve(chunks.saturating_sub(self.full.len()))?;
        (self.tail).try_reserve_exact(CHUNK.saturating_sub(self.tail.len()))?;
        let spare = chunks.saturating_sub(self.full.len() + 1);
        (self.spare).try_reserve(spare.saturating_sub(self.spare.len()))?;
        while self.spare.len() < spare {
            let mut chunk = Vec::new();
            chunk.try_reserve_exact(CHUNK)?;
            self.spare.push(chunk);
        }
        Ok(())
    }

    /// Elements it holds without allocating a chunk's room.
    pub fn capacity(&self) -> usize {
        (self.full.len() + self.spare.len()) * CHUNK + self.tail.capacity()
    }

    /// Where the chunks' elements are, in order (tests: an array that grew within its room
    /// moved no element).
    #[cfg(test)]
    pub fn chunk_addresses(&self) -> Vec<*const T> {
        let mut out: Vec<*const T> = self.full.iter().map(|c| c.as_ptr()).collect();
        out.push(self.tail.as_ptr());
        out.extend(self.spare.iter().rev().map(|c| c.as_ptr()));
        out
    }
}

/// Whether chunk `c` holds any element of the range `(start, end)` (chunks before the
/// range's are skipped by the callers, so this says whether the range still reaches it).
fn touches((start, end): (usize, usize), c: usize) -> bool {
    start < end && c * CHUNK < end
}

/// The part of the range `(start, end)` in chunk `c` (of `len` elements), as indices into the
/// chunk.
fn cut((start, end): (usize, usize), c: usize, len: usize) -> Range<usize> {
    let at = c * CHUNK;
    let a = start.saturating_sub(at).min(len);
    a..end.saturating_sub(at).clamp(a, len)
}

impl<T: Copy> std::ops::Index<usize> for Chunked<T> {
    type Output = T;
    fn index(&self, i: usize) -> &T {
        match self.full.get(i / CHUNK) {
            Some(chunk) => &chunk[i % CHUNK],
            None => &self.tail[i - self.full.len() * CHUNK],
        }
    }
}

impl<T: Copy> std::ops::IndexMut<usize> for Chunked<T> {
    fn index_mut(&mut self, i: usize) -> &mut T {
        let full = self.full.len();
        match self.full.get_mut(i / CHUNK) {
            // A shared chunk is copied first.
            Some(chunk) => &mut Arc::make_mut(chunk)[i % CHUNK],
            None => &mut self.tail[i - full * CHUNK],
        }
    }
}

impl<T: Copy> FromIterator<T> for Chunked<T> {
    fn from_iter<I: IntoIterator<Item = T>>(iter: I) -> Self {
        let mut out = Self::default();
        for v in iter {
            out.push(v);
        }
        out
    }
}

impl<T: Copy + PartialEq> PartialEq for Chunked<T> {
    fn eq(&self, other: &Self) -> bool {
        self.len() == other.len() && self.iter().eq(other.iter())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A copy shares every chunk; writes to either copy one chunk and leave the other as it
    /// was; pushes and pops across chunk boundaries keep the order; reserved room is used.
    #[test]
    fn a_copy_shares_until_written() {
        let n = 3 * CHUNK + 7;
        let mut a: Chunked<u64> = (0..n as u64).collect();
        assert_eq!(a.len(), n);
        assert!(a.iter().copied().eq(0..n as u64));
        let b = a.clone();
        // The full chunks shared, the tail copied.
        let (x, y) = (a.chunk_addresses(), b.chunk_addresses());
        assert_eq!((x.len(), y.len()), (4, 4));
        assert!(x[..3] == y[..3] && x[3] != y[3]);
        a[CHUNK + 3] = 1_000_000;
        a[5] = 7;
        assert_eq!(
            (a[CHUNK + 3], b[CHUNK + 3], a[5], b[5]),
            (1_000_000, CHUNK as u64 + 3, 7, 5)
        );
        // The two chunks written were copied; the third full one is still shared.
        let shared = (a.full.iter().zip(&b.full)).filter(|(x, y)| Arc::ptr_eq(x, y));
        assert_eq!(shared.count(), 1);
        // Appending to a copy leaves the original.
        let mut c = b.clone();
        c.push(42);
        assert_eq!((c.len(), b.len(), c[n]), (n + 1, n, 42));
        assert!(b.iter().copied().eq(0..n as u64));
        // Pop back across a chunk boundary.
        for _ in 0..8 {
            c.pop();
        }
        assert_eq!(c.len(), 3 * CHUNK);
        assert_eq!(c.get(3 * CHUNK), None);
        assert_eq!(c[3 * CHUNK - 1], 3 * CHUNK as u64 - 1);
        // Writing through iter_mut leaves the snapshot.
        for v in c.iter_mut() {
            *v += 1;
        }
        assert!(c.iter().copied().eq(1..=3 * CHUNK as u64));
        assert!(b.iter().copied().eq(0..n as u64));
        // A pop from an empty tail takes the last full chunk back as the tail.
        assert_eq!(c.pop(), Some(3 * CHUNK as u64));
        assert_eq!(
            (c.len(), c[3 * CHUNK - 2]),
            (3 * CHUNK - 1, 3 * CHUNK as u64 - 1)
        );
        c.push(5);
        assert_eq!((c.len(), c[3 * CHUNK - 1]), (3 * CHUNK, 5));
        // Room ahead: pushes into reserved chunks allocate nothing.
        let mut d: Chunked<u64> = Chunked::default();
        d.try_reserve(2 * CHUNK + 1).unwrap();
        assert_eq!(d.capacity(), 3 * CHUNK);
        let room = d.chunk_addresses();
        for v in 0..(2 * CHUNK + 1) as u64 {
            d.push(v);
            if v == CHUNK as u64 {
                // A copy in between (a renewal's snapshot) leaves the room where it was.
                let _ = d.clone();
            }
        }
        assert_eq!(d.chunk_addresses(), room);
        assert_eq!(d.capacity(), 3 * CHUNK);
        assert_eq!(d.iter().count(), 2 * CHUNK + 1);
        assert_eq!(d.pop(), Some(2 * CHUNK as u64));
        assert_eq!(Chunked::<u64>::default().pop(), None);
    }

    /// The slices of a range hold exactly its elements, in order, wherever its ends fall
    /// (inside a chunk, on a boundary, in the tail, a full tail, empty).
    #[test]
    fn the_slices_of_a_range_are_its_elements() {
        for n in [0, 5, CHUNK, 2 * CHUNK + 3] {
            let a: Chunked<u64> = (0..n as u64).collect();
            let cuts = [
                0,
                1,
                CHUNK - 1,
                CHUNK,
                CHUNK + 1,
                2 * CHUNK,
                n.saturating_sub(1),
                n,
            ];
            for &lo in cuts.iter().filter(|&&c| c <= n) {
                for &hi in cuts.iter().filter(|&&c| lo <= c && c <= n) {
                    let got: Vec<u64> = a.slices_in(lo..hi).flatten().copied().collect();
                    assert!(
                        got.iter().copied().eq(lo as u64..hi as u64),
                        "{n}: {lo}..{hi}"
                    );
                    // Written through the mutable slices: that range only, in a copy whose
                    // chunks outside it stay shared with the original.
                    let mut b = a.clone();
                    for v in b.slices_in_mut(lo..hi).flatten() {
                        *v += 1_000_000;
                    }
                    let moved =
                        |i: usize| i as u64 + if (lo..hi).contains(&i) { 1_000_000 } else { 0 };
                    assert!(
                        b.iter().copied().eq((0..n).map(moved)),
                        "{n}: {lo}..{hi} written"
                    );
                    let shared = (a.full.iter().zip(&b.full).enumerate())
                        .filter(|(_, (x, y))| Arc::ptr_eq(x, y))
                        .map(|(c, _)| c);
                    let outside = |c: usize| lo == hi || c * CHUNK >= hi || (c + 1) * CHUNK <= lo;
                    assert!(
                        shared.eq((0..a.full.len()).filter(|&c| outside(c))),
                        "{n}: {lo}..{hi}"
                    );
                }
            }
        }
    }
}
