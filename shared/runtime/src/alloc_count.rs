//! Test-only global allocator that counts the allocations of the calling thread, so a test can
//! assert that a piece of code does not allocate (other test threads do not disturb the count).

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

thread_local! {
    // `const` initialisation: no lazy registration, so reading it never allocates itself.
    static ALLOCATIONS: Cell<u64> = const { Cell::new(0) };
    static FREES: Cell<u64> = const { Cell::new(0) };
}

struct Counting;

// SAFETY: every method forwards to `System` with the same arguments, which upholds
// `GlobalAlloc`'s contract; the only addition is a thread-local counter increment, which
// neither allocates nor unwinds.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        ALLOCATIONS.with(|c| c.set(c.get() + 1));
        // SAFETY: the caller's `layout` is passed on unchanged.
        unsafe { System.alloc(layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        ALLOCATIONS.with(|c| c.set(c.get() + 1));
        // SAFETY: the caller's `layout` is passed on unchanged.
        unsafe { System.alloc_zeroed(layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        ALLOCATIONS.with(|c| c.set(c.get() + 1));
        // SAFETY: `ptr` was allocated by `System` (through this allocator) with `layout`.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        FREES.with(|c| c.set(c.get() + 1));
        // SAFETY: `ptr` was allocated by `System` (through this allocator) with `layout`.
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

/// Allocations (alloc, alloc_zeroed, realloc) made by the current thread while `f` runs.
pub fn allocations_during<R>(f: impl FnOnce() -> R) -> (R, u64) {
    let before = ALLOCATIONS.with(Cell::get);
    let r = f();
    (r, ALLOCATIONS.with(Cell::get) - before)
}

/// Allocations (as [`allocations_during`]) and frees made by the current thread while `f`
/// runs.
pub fn allocations_and_frees_during<R>(f: impl FnOnce() -> R) -> (R, u64, u64) {
    let before = FREES.with(Cell::get);
    let (r, allocations) = allocations_during(f);
    (r, allocations, FREES.with(Cell::get) - before)
}

#[test]
fn the_counter_sees_an_allocation_and_nothing_else() {
    let (v, n) = allocations_during(|| vec![1u8; 16]);
    assert_eq!((v.len(), n), (16, 1));
    let (_, n) = allocations_during(|| 2 + 2);
    assert_eq!(n, 0);
    let (_, n, f) = allocations_and_frees_during(|| drop(vec![1u8; 16]));
    assert_eq!((n, f), (1, 1));
}
