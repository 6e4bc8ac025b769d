"""Python client of the disparity service: numpy arrays in and out, typed errors, polite retries.

    from crestereo_pp.client import StereoClient
    with StereoClient("http://127.0.0.1:8000") as service:
        result = service.disparity(left_rgb, right_rgb, model="lite")
    result.disparity, result.uncertainty            # float32 HxW

`service.point_cloud(left, right, focal_px=721.0, baseline_m=0.54)` gives a `PointCloud`. The
options of each call are `Options` keywords. `service.stream(warm_iters=3)` opens a WebSocket for
a video's pairs (`DisparityStream.send(left, right)`, each frame warm-started from the previous
one). `AsyncStereoClient` is the same with `await` (its stream with `async with`). Only httpx,
websockets, numpy and OpenCV (to encode arrays as PNG) are needed; nothing of the server is
imported.
"""

from .stereo_client import (
    AsyncDisparityStream,
    AsyncStereoClient,
    Camera,
    Computation,
    DisparityResult,
    DisparityStream,
    Options,
    PointCloud,
    RowOffset,
    ServiceError,
    StereoClient,
    service_address,
)

__all__ = [
    "AsyncDisparityStream",
    "AsyncStereoClient",
    "Camera",
    "Computation",
    "DisparityResult",
    "DisparityStream",
    "Options",
    "PointCloud",
    "RowOffset",
    "ServiceError",
    "StereoClient",
    "service_address",
]
