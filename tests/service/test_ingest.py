"""Fair ingest: lanes per camera served in turn, poses and infos apart from images, bounds in
count and bytes, a flooding camera paying for its own flood."""

import threading

from posefuse.service.ingest import FairIngest, IngestConfig


def _served(ingest: FairIngest) -> list[tuple[str, str, object]]:
    out = []
    while (got := ingest.get_nowait()) is not None:
        out.append(got)
        ingest.done(got[0])
    return out


def test_lanes_share_the_decoders_by_decoding_time_small_messages_first():
    ingest = FairIngest()
    for k in range(5):
        ingest.put("flood", "image", f"f{k}", 1000)
    ingest.put("cam0", "image", "c0", 1000)
    ingest.put("cam0", "pose", "p0", 10)
    order = []
    while (got := ingest.get_nowait()) is not None:
        cam, _, item = got
        order.append(item)
        ingest.done(cam, 0.4 if cam == "flood" else 0.01)  # a big PNG, a small JPEG
        if item == "f2":  # cam0 goes on sending while the flood waits
            for k in range(1, 4):
                ingest.put("cam0", "pose", f"p{k}", 10)
                ingest.put("cam0", "image", f"c{k}", 1000)
    assert ingest.dropped == {"image_ingest_full": 1}  # the flood's oldest (4 per camera)
    assert order[:3] == ["f1", "p0", "c0"]  # a pose first, then the cheaper lane's image
    # once the flood has cost more, every frame of cam0 is decoded before its next image
    after = order[order.index("f2") + 1 :]
    assert after[:6] == ["p1", "p2", "p3", "c1", "c2", "c3"] and after[6:] == ["f3", "f4"]
    assert ingest.pending() == 0 and ingest.pending_bytes() == 0


def test_a_new_lane_is_expected_as_dear_as_the_dearest_recent_image():
    ingest = FairIngest()
    ingest.put("big", "image", "b0", 1)
    cam, *_ = ingest.get_nowait()
    ingest.done(cam, 0.5)
    ingest.put("cam0", "image", "c0", 1)
    cam, *_ = ingest.get_nowait()
    ingest.done(cam, 0.01)
    for k in range(16):  # junk ids, one big image each, then cam0's next frame
        ingest.put(f"junk{k}", "image", f"j{k}", 1)
    ingest.put("cam0", "image", "c1", 1)
    assert ingest.get_nowait()[2] == "c1"  # known cheap: before every unknown lane


def test_a_burst_of_400_poses_is_kept_and_beyond_the_bound_the_oldest_go():
    ingest = FairIngest()
    for k in range(400):
        ingest.put("cam0", "pose", k, 120)
    for k in range(4):
        ingest.put("cam0", "image", f"i{k}", 10**6)
    served = _served(ingest)
    assert [item for _, kind, item in served if kind == "pose"] == list(range(400))
    assert not ingest.dropped
    small = FairIngest(IngestConfig(small_per_camera=100))
    for k in range(400):
        small.put("cam0", "pose", k, 120)
    assert [item for *_, item in _served(small)] == list(range(300, 400))  # the newest kept
    assert small.dropped == {"pose_ingest_full": 300}


def test_bytes_are_bounded_and_the_camera_holding_the_most_pays():
    ingest = FairIngest(IngestConfig(max_bytes=10_000, images_per_camera=10))
    ingest.put("cam0", "image", "good", 1000)
    for k in range(20):
        ingest.put(f"flood{k % 3}", "image", k, 3000)
    assert ingest.pending_bytes() <= 10_000
    items = {item for *_, item in _served(ingest)}
    assert "good" in items
    assert ingest.dropped["image_ingest_full"] == 20 - 3
    assert not FairIngest(IngestConfig(max_bytes=100)).put("cam", "image", "x", 101)
    assert not FairIngest(IngestConfig(small_bytes_per_camera=100)).put("cam", "pose", "x", 101)


def test_a_camera_is_never_served_to_two_decoders_at_once():
    ingest = FairIngest()
    for k in range(3):
        ingest.put("a", "image", k, 1)
    ingest.put("b", "image", "b0", 1)
    first = ingest.get_nowait()
    second = ingest.get_nowait()
    assert {first[0], second[0]} == {"a", "b"}
    assert ingest.get_nowait() is None  # a is busy, b is empty
    ingest.done("a")
    assert ingest.get_nowait()[2] == 1
    ingest.done("b")
    ingest.done("a")
    assert ingest.get_nowait()[2] == 2


def test_decoder_threads_get_every_message_of_a_camera_in_order():
    ingest = FairIngest(IngestConfig(small_per_camera=5000))
    seen: dict[str, list[int]] = {}
    lock = threading.Lock()
    stop = threading.Event()

    def decoder():
        while not stop.is_set():
            got = ingest.get(timeout=0.05)
            if got is None:
                continue
            with lock:
                seen.setdefault(got[0], []).append(got[2])
            ingest.done(got[0])

    threads = [threading.Thread(target=decoder) for _ in range(3)]
    for t in threads:
        t.start()
    for k in range(2000):
        ingest.put(f"cam{k % 7}", "pose", k, 100)
    while ingest.pending():
        threading.Event().wait(0.01)
    stop.set()
    for t in threads:
        t.join()
    for cam, items in seen.items():
        assert items == sorted(items) and len(items) == len(range(int(cam[3:]), 2000, 7))


def test_lanes_are_bounded_idle_ones_seen_longest_ago_leave():
    ingest = FairIngest(IngestConfig(max_lanes=8))
    for k in range(100):
        ingest.put(f"junk{k}", "pose", k, 10)
        cam, *_ = ingest.get_nowait()
        ingest.done(cam, 0.001)
    assert len(ingest._lanes) <= 8


def test_images_of_cameras_without_info_wait_for_those_with_it():
    """15 new camera ids flood images and never send an info; cam0, with its info, starts
    sending after them: each of its images is decoded next, and the flood once cam0 is done.
    A camera whose info comes meanwhile is served in the first rank from then on."""
    with_info = {"cam0"}
    ingest = FairIngest(has_info=with_info.__contains__)
    for k in range(30):
        ingest.put(f"flood{k % 15}", "image", f"f{k}", 1000)
    ingest.put("cam0", "image", "c0", 1000)
    order = []
    while (got := ingest.get_nowait()) is not None:
        cam, _, item = got
        order.append(item)
        ingest.done(cam, 0.4 if cam.startswith("flood") else 0.01)
        if len(order) == 2:  # cam0 goes on sending, and flood3 sends its info, during the flood
            ingest.put("cam0", "image", "c1", 1000)
            with_info.add("flood3")
            ingest.put("flood3", "info", "i3", 10)
    assert order[0] == "c0" and order[1].startswith("f")  # before: a whole round of f, then c0
    assert order[2:4] == ["i3", "c1"] and order[4] == "f3"  # flood3's image, with its info
    assert len(order) == 33 and ingest.pending() == 0
