"""Telesplat clients: the asyncio streaming client, the REST client, the CLI, the web page.

Imports the protocol package only (never server/, never torch); OpenCV is loaded when a frame
image is first decoded.
"""

from .images import decode_depth, decode_image, save_frame
from .motion_file import Motion, load_motion
from .rest import ApiError, RestClient, SseEvent, parse_sse
from .stream import Backoff, StreamClient, StreamError, stream_url

__all__ = [
    "ApiError", "Backoff", "Motion", "RestClient", "SseEvent", "StreamClient", "StreamError",
    "decode_depth", "decode_image", "load_motion", "parse_sse", "save_frame", "stream_url",
]
