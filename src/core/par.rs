//! Minimal data parallelism over scoped threads (no dependency): a slice is cut into one
//! contiguous chunk per thread. Chunk boundaries depend only on the length and the thread
//! count, and every element is written by exactly one thread, so results do not depend
//! on scheduling.

/// Number of worker threads to use when the caller asks for 0 ("all cores").
pub fn default_threads() -> usize {
    std::thread::available_parallelism().map_or(1, |n| n.get())
}

/// Threads worth using for `items` light items (a few arithmetic operations or copies
/// each): up to `threads` (0 = all cores) but at least `per_thread` items each, since a
/// scoped thread costs tens of microseconds to start. At least 1.
pub fn threads_for(items: usize, per_thread: usize, threads: usize) -> usize {
    let threads = if threads == 0 {
        default_threads()
    } else {
        threads
    };
    threads.min(items / per_thread.max(1)).max(1)
}

/// Calls `f(first_item, chunk)` on contiguous chunks of `data`, each a whole number of
/// `item`-sized items, on up to `threads` threads (0 = all cores).
pub fn for_chunks_mut<T: Send, F>(data: &mut [T], item: usize, threads: usize, f: F)
where
    F: Fn(usize, &mut [T]) + Sync,
{
    let item = item.max(1);
    let items = data.len() / item;
    let threads = if threads == 0 {
        default_threads()
    } else {
        threads
    };
    let threads = threads.min(items.max(1));
    if threads <= 1 || items < 64 {
        f(0, data);
        return;
    }
    let per = items.div_ceil(threads);
    std::thread::scope(|s| {
        let f = &f;
        let mut rest = data;
        let mut first = 0;
        while !rest.is_empty() {
            let take = (per * item).min(rest.len());
            let (head, tail) = rest.split_at_mut(take);
            rest = tail;
            let start = first;
            first += take / item;
            if rest.is_empty() {
                f(start, head);
            } else {
                s.spawn(move || f(start, head));
            }
        }
    });
}

/// Like [`for_chunks_mut`] over two slices of equal item count, cut at the same items.
pub fn for_chunks_mut2<A: Send, B: Send, F>(a: &mut [A], b: &mut [B], threads: usize, f: F)
where
    F: Fn(usize, &mut [A], &mut [B]) + Sync,
{
    let items = a.len().min(b.len());
    let threads = if threads == 0 {
        default_threads()
    } else {
        threads
    };
    let threads = threads.min(items.max(1));
    if threads <= 1 || items < 64 {
        f(0, a, b);
        return;
    }
    let per = items.div_ceil(threads);
    std::thread::scope(|s| {
        let f = &f;
        let (mut ra, mut rb) = (a, b);
        let mut first = 0;
        while first < items {
            let take = per.min(items - first);
            let (ha, ta) = ra.split_at_mut(take);
            let (hb, tb) = rb.split_at_mut(take);
            ra = ta;
            rb = tb;
            let start = first;
            first += take;
            if first >= items {
                f(start, ha, hb);
            } else {
                s.spawn(move || f(start, ha, hb));
            }
        }
    });
}

/// `f(0), f(1), …, f(count − 1)` on up to `threads` threads (0 = all cores), in
/// contiguous runs of indices, returned in index order. For a few large items (unlike
/// [`for_chunks_mut`], which keeps small slices on one thread).
pub fn map<T: Send, F>(count: usize, threads: usize, f: F) -> Vec<T>
where
    F: Fn(usize) -> T + Sync,
{
    let threads = if threads == 0 {
        default_threads()
    } else {
        threads
    }
    .min(count.max(1));
    if threads <= 1 {
        return (0..count).map(f).collect();
    }
    let per = count.div_ceil(threads);
    std::thread::scope(|s| {
        let f = &f;
        let runs: Vec<_> = (0..count)
            .step_by(per)
            .map(|first| {
                s.spawn(move || (first..(first + per).min(count)).map(f).collect::<Vec<T>>())
            })
            .collect();
        runs.into_iter()
            .flat_map(|r| r.join().unwrap_or_else(|e| std::panic::resume_unwind(e)))
            .collect()
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn threads_for_keeps_enough_items_per_thread() {
        assert_eq!(threads_for(100, 10, 4), 4);
        assert_eq!(threads_for(39, 10, 4), 3);
        assert_eq!(threads_for(9, 10, 4), 1);
        assert_eq!(threads_for(0, 10, 4), 1);
        assert_eq!(threads_for(100, 0, 2), 2);
        assert!(threads_for(usize::MAX, 1, 0) == default_threads());
    }
}
