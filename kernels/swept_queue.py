"""The swept detection's serial event queue (the CPU's resolution; ``kernels/collide.py`` ``resolve_swept`` with
``queue``): a window's events one by one in the strict time order, from a binary heap of the parcels' event keys.

A module of its own so that a CUDA device, which resolves in rounds, never compiles it (NVRTC took over ten minutes
on the inlined search loops of ``swept_queue``; the CPU compiles it in about a minute, once, into the kernel cache).
"""

from __future__ import annotations

import warp as wp

from kernels.cell_list import range_count, range_slots, range_slots_pair, search_box, search_box_pair
from kernels.collide import (
    EVENT_NONE,
    NEAR_MARGIN,
    SweptArgs,
    event_key,
    event_partner,
    first_touch,
    list_far_reaching,
    paths_near,
    relative_position,
    resolve_event_row,
    resolve_wall_row,
    wall_touch,
    write_event_row,
)
from kernels.forest import Forest


@wp.func
def heap_less(key_a: wp.int64, owner_a: int, key_b: wp.int64, owner_b: int):
    return key_a < key_b or (key_a == key_b and owner_a < owner_b)


@wp.func
def heap_push(heap_key: wp.array(dtype=wp.int64), heap_owner: wp.array(dtype=wp.int32),
              heap_size: wp.array(dtype=wp.int32), key: wp.int64, owner: int):
    """Binary min-heap of (event key, owner) entries, ordered by key then owner: insert (sift up). The caller keeps
    the size below the capacity."""
    k = heap_size[0]
    heap_size[0] = k + 1
    while k > 0:
        parent = (k - 1) / 2
        if not heap_less(key, owner, heap_key[parent], heap_owner[parent]):
            break
        heap_key[k] = heap_key[parent]
        heap_owner[k] = heap_owner[parent]
        k = parent
    heap_key[k] = key
    heap_owner[k] = owner


@wp.func
def heap_pop(heap_key: wp.array(dtype=wp.int64), heap_owner: wp.array(dtype=wp.int32),
             heap_size: wp.array(dtype=wp.int32)):
    """Remove the smallest entry (sift down) and return its owner (its key: ``heap_key[0]`` before the call); the
    heap must not be empty."""
    top = heap_owner[0]
    n = heap_size[0] - 1
    heap_size[0] = n
    if n > 0:
        last_key = heap_key[n]
        last_owner = heap_owner[n]
        k = int(0)
        while 2 * k + 1 < n:
            c = 2 * k + 1
            if c + 1 < n and heap_less(heap_key[c + 1], heap_owner[c + 1], heap_key[c], heap_owner[c]):
                c = c + 1
            if not heap_less(heap_key[c], heap_owner[c], last_key, last_owner):
                break
            heap_key[k] = heap_key[c]
            heap_owner[k] = heap_owner[c]
            k = c
        heap_key[k] = last_key
        heap_owner[k] = last_owner
    return top


@wp.func
def heap_rebuild(args: SweptArgs, heap_key: wp.array(dtype=wp.int64), heap_owner: wp.array(dtype=wp.int32),
                 heap_size: wp.array(dtype=wp.int32)):
    """The queue anew from the parcels' keys (one entry each), dropping the stale entries."""
    heap_size[0] = 0
    for i in range(args.event_key.shape[0]):
        key = args.event_key[i]
        if key != EVENT_NONE:
            heap_push(heap_key, heap_owner, heap_size, key, i)


@wp.func
def queue_offer(args: SweptArgs, heap_key: wp.array(dtype=wp.int64), heap_owner: wp.array(dtype=wp.int32),
                heap_size: wp.array(dtype=wp.int32), i: int, key: wp.int64):
    """Offer an event to parcel i: its key becomes the smaller, queued when it changed (the serial ``offer_event``;
    a stale entry is skipped when popped)."""
    if key < args.event_key[i]:
        args.event_key[i] = key
        if heap_size[0] < heap_key.shape[0]:
            heap_push(heap_key, heap_owner, heap_size, key, i)
        else:
            heap_rebuild(args, heap_key, heap_owner, heap_size)  # full of stale entries (capacity > n)


@wp.func
def queue_pair(args: SweptArgs, particle_v: wp.array(dtype=wp.vec3), heap_key: wp.array(dtype=wp.int64),
               heap_owner: wp.array(dtype=wp.int32), heap_size: wp.array(dtype=wp.int32), i: int, j: int):
    """The pair's first touch, if any, offered to both parcels (``offer_pair``)."""
    t = first_touch(args, particle_v, wp.min(i, j), wp.max(i, j))
    if t >= 0.0:
        queue_offer(args, heap_key, heap_owner, heap_size, i, event_key(t, args.dt, j))
        queue_offer(args, heap_key, heap_owner, heap_size, j, event_key(t, args.dt, i))


@wp.func
def queue_restart(args: SweptArgs, particle_v: wp.array(dtype=wp.vec3), heap_key: wp.array(dtype=wp.int64),
                  heap_owner: wp.array(dtype=wp.int32), heap_size: wp.array(dtype=wp.int32), i: int):
    """A search's start for live parcel i: its key cleared, its wall crossing (if any) offered and queued."""
    args.event_key[i] = EVENT_NONE
    t_wall = wall_touch(args, particle_v, i)
    if t_wall >= 0.0:
        queue_offer(args, heap_key, heap_owner, heap_size, i, event_key(t_wall, args.dt, i))


@wp.func
def queue_predict(args: SweptArgs, particle_v: wp.array(dtype=wp.vec3), heap_key: wp.array(dtype=wp.int64),
                  heap_owner: wp.array(dtype=wp.int32), heap_size: wp.array(dtype=wp.int32), i: int):
    """Parcel i's events searched anew (its key cleared first): its wall crossing and every pair it may meet (the
    cell list out to partners of path bound <= bound_cut, the rest listed), offered to both parcels."""
    if args.particle_alive[i] == 0:
        args.event_key[i] = EVENT_NONE
        return
    queue_restart(args, particle_v, heap_key, heap_owner, heap_size, i)
    ri = args.particle_radius[i]
    mi = args.anchor[i]
    extent_i = ri + args.path_bound[i]
    cut = args.bound_cut
    radius = (ri + args.max_radius + args.path_bound[i] + wp.min(cut, args.reach_max[0])) * NEAR_MARGIN
    lo, hi = search_box(args.cells, mi, radius)
    for k_range in range(range_count(args.cells, lo, hi)):
        begin, end = range_slots(args.cells, lo, hi, k_range, mi, radius)
        for slot in range(begin, end):
            j = args.cells.slot_point[slot]
            if j != i and args.path_bound[j] <= cut:
                if paths_near(args, mi, extent_i, j, args.cells.slot_position[slot]):
                    queue_pair(args, particle_v, heap_key, heap_owner, heap_size, i, j)
    for slot in range(args.bound_count[0]):
        j = args.bound_index[slot]
        if j != i and args.path_bound[j] > cut:
            if paths_near(args, mi, extent_i, j, args.anchor[j]):
                queue_pair(args, particle_v, heap_key, heap_owner, heap_size, i, j)


@wp.func
def queue_predict_two(args: SweptArgs, particle_v: wp.array(dtype=wp.vec3), heap_key: wp.array(dtype=wp.int64),
                      heap_owner: wp.array(dtype=wp.int32), heap_size: wp.array(dtype=wp.int32), i: int, j: int):
    """``queue_predict`` of i and of j (the two parcels of an event, i != j, both live) in one walk of the union of
    their balls: a candidate near both is read once. The same offers, so the same keys (a key is the smallest
    offer, whatever their order) and the same queued events as the two searches one after the other."""
    queue_restart(args, particle_v, heap_key, heap_owner, heap_size, i)
    queue_restart(args, particle_v, heap_key, heap_owner, heap_size, j)
    cut = args.bound_cut
    partner_bound = args.max_radius + wp.min(cut, args.reach_max[0])
    mi = args.anchor[i]
    extent_i = args.particle_radius[i] + args.path_bound[i]
    radius_i = (extent_i + partner_bound) * NEAR_MARGIN
    mj = args.anchor[j]
    extent_j = args.particle_radius[j] + args.path_bound[j]
    radius_j = (extent_j + partner_bound) * NEAR_MARGIN
    lo, hi = search_box_pair(args.cells, mi, radius_i, mj, radius_j)
    for k_range in range(range_count(args.cells, lo, hi)):
        begin, end = range_slots_pair(args.cells, lo, hi, k_range, mi, radius_i, mj, radius_j)
        for slot in range(begin, end):
            c = args.cells.slot_point[slot]
            if args.path_bound[c] <= cut:
                m_c = args.cells.slot_position[slot]
                if c != i and paths_near(args, mi, extent_i, c, m_c):
                    queue_pair(args, particle_v, heap_key, heap_owner, heap_size, i, c)
                if c != j and paths_near(args, mj, extent_j, c, m_c):
                    queue_pair(args, particle_v, heap_key, heap_owner, heap_size, j, c)
    for slot in range(args.bound_count[0]):
        c = args.bound_index[slot]
        if args.path_bound[c] > cut:
            m_c = args.anchor[c]
            if c != i and paths_near(args, mi, extent_i, c, m_c):
                queue_pair(args, particle_v, heap_key, heap_owner, heap_size, i, c)
            if c != j and paths_near(args, mj, extent_j, c, m_c):
                queue_pair(args, particle_v, heap_key, heap_owner, heap_size, j, c)


@wp.kernel
def swept_queue(
    args_store: wp.array(dtype=SweptArgs),
    forest: Forest,
    heap_key: wp.array(dtype=wp.int64),
    heap_owner: wp.array(dtype=wp.int32),
    heap_size: wp.array(dtype=wp.int32),
    max_pops: int,
    # outputs
    particle_v: wp.array(dtype=wp.vec3),
    particle_omega: wp.array(dtype=wp.vec3),
    calls: wp.array(dtype=wp.int32),
    collisions: wp.array(dtype=wp.int32),
    event_count: wp.array(dtype=wp.int32),
    cap_hit: wp.array(dtype=wp.int32),
):
    """The window's events one by one in time order (one thread: the CPU's serial resolution; the keys are those of
    the window's full search, ``swept_find`` in its first round). The queue holds (key, owner) entries ordered as
    the strict order's global minimum: the smallest key K = (time bits, p) names the event of p with the partner
    p's own key names (``ordering="sequential"``'s pair: the holder of K and p); an entry whose owner's key changed
    since is stale and skipped; a wall event is resolved when its crossing is still there. After an event both
    parcels are searched anew (their events offered to both sides and queued). A parcel whose partner moved keeps
    its stale key until it is popped and searched anew: every event earlier than the stale key is still offered to
    it, so none is missed or resolved out of order; where the keys do not agree (a stale one among them) the parcels
    involved are searched anew. ``max_pops``: a bound on the entries popped (an inelastic collapse), ``cap_hit`` set
    when it stops the window."""
    args = args_store[0]
    heap_rebuild(args, heap_key, heap_owner, heap_size)
    events = int(0)
    pops = int(0)
    while heap_size[0] > 0:
        if pops >= max_pops:
            cap_hit[0] = 1
            break
        pops = pops + 1
        key = heap_key[0]
        x = heap_pop(heap_key, heap_owner, heap_size)
        if args.event_key[x] != key:
            continue  # stale: the parcel's event changed since it was queued
        p = event_partner(key)
        if p == x:
            t_wall = wall_touch(args, particle_v, x)
            if t_wall < 0.0:
                queue_predict(args, particle_v, heap_key, heap_owner, heap_size, x)
                continue
            args.wall_i[0] = x
            args.wall_time[0] = t_wall
            resolve_wall_row(args, particle_v, particle_omega, 0)
            list_far_reaching(args, x)
            queue_predict(args, particle_v, heap_key, heap_owner, heap_size, x)
            events = events + 1
            continue
        key_p = args.event_key[p]
        b = int(-1)
        if key_p != EVENT_NONE:
            b = event_partner(key_p)
        q_bits = (key >> wp.int64(32)) << wp.int64(32)
        if b < 0 or b == p or key_p != (q_bits | wp.int64(b)) or args.event_key[b] != (q_bits | wp.int64(p)):
            # the keys do not agree (a stale key among them): the parcels involved are searched anew
            if (key_p >> wp.int64(32)) > (key >> wp.int64(32)):
                # p's key, a lower bound of p's next event (a new event is offered to both sides), is later: the
                # event x's key names is gone, x's key alone is stale
                queue_predict(args, particle_v, heap_key, heap_owner, heap_size, x)
                continue
            queue_predict(args, particle_v, heap_key, heap_owner, heap_size, x)
            queue_predict(args, particle_v, heap_key, heap_owner, heap_size, p)
            if b >= 0 and b != p and b != x:
                queue_predict(args, particle_v, heap_key, heap_owner, heap_size, b)
            continue
        i = wp.min(p, b)
        j = wp.max(p, b)
        t = first_touch(args, particle_v, i, j)
        dist = float(0.0)
        s = wp.vec3(0.0)
        if t >= 0.0:
            s = relative_position(args, particle_v, i, j, t)
            dist = wp.length(s)
        if dist <= 0.0:
            queue_predict(args, particle_v, heap_key, heap_owner, heap_size, i)
            queue_predict(args, particle_v, heap_key, heap_owner, heap_size, j)
            continue
        write_event_row(args, particle_v, 0, i, j, t, s / dist)
        resolve_event_row(args, forest, particle_v, calls, collisions, 0)
        list_far_reaching(args, i)
        list_far_reaching(args, j)
        queue_predict_two(args, particle_v, heap_key, heap_owner, heap_size, i, j)
        if x != i and x != j:  # the holder of K whose entry was taken: queued again (stale now: searched anew)
            if heap_size[0] < heap_key.shape[0]:
                heap_push(heap_key, heap_owner, heap_size, args.event_key[x], x)
            else:
                heap_rebuild(args, heap_key, heap_owner, heap_size)
        events = events + 1
    event_count[0] = event_count[0] + events
