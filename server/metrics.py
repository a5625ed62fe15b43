"""Prometheus metrics, in a registry of the app's own (several apps may live in one process)."""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest

LATENCY_BUCKETS_MS = (2, 5, 10, 20, 35, 50, 75, 100, 150, 250, 500, 1000, 2500)


class ServerMetrics:
    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        r = self.registry
        self.sessions = Gauge("telesplat_sessions", "Streaming sessions open now", registry=r)
        self.sessions_total = Counter("telesplat_sessions_opened", "Sessions opened",
                                      registry=r)
        self.sessions_refused = Counter("telesplat_sessions_refused",
                                        "Sessions refused, by reason", ["reason"], registry=r)
        self.frames = Counter("telesplat_frames", "Frames sent, by codec", ["codec"],
                              registry=r)
        self.dropped = Counter("telesplat_frames_dropped", "Inputs superseded before they got "
                               "a frame of their own", registry=r)
        self.coalesced = Counter("telesplat_drives_coalesced",
                                 "Drives merged into a later one before rendering", registry=r)
        self.bytes_sent = Counter("telesplat_frame_bytes", "Encoded frame bytes sent",
                                  registry=r)
        self.messages = Counter("telesplat_messages", "Client messages received, by type",
                                ["type"], registry=r)
        self.errors = Counter("telesplat_errors", "Error messages sent, by code", ["code"],
                              registry=r)
        self.stage_ms = Histogram("telesplat_stage_ms", "Milliseconds per frame stage",
                                  ["stage"], buckets=LATENCY_BUCKETS_MS, registry=r)
        self.render_queue = Gauge("telesplat_render_queue", "Renders queued or running",
                                  registry=r)
        self.avatars = Gauge("telesplat_avatars", "Avatars in the registry", registry=r)
        self.render_workers = Gauge("telesplat_render_workers", "render_backend ray: render "
                                    "workers by state (starting, ready)", ["state"], registry=r)
        self.render_workers_lost = Gauge("telesplat_render_workers_lost", "render_backend ray: "
                                         "render workers lost since start-up", registry=r)
        self.webrtc_dc_dropped_chunks = Counter(
            "telesplat_webrtc_dc_dropped_chunks", "WebRTC data-channel SCTP chunks dropped "
            "before reassembly, unacknowledged, by reason (window: past "
            "webrtc_receive_window_bytes; streams: past webrtc_max_sctp_streams; duplicate: "
            "a copy of one waiting; closed: the peer refused or closing)", ["reason"],
            registry=r)
        self.webrtc_dc_dropped_bytes = Counter(
            "telesplat_webrtc_dc_dropped_bytes", "User-data bytes of those chunks, by reason",
            ["reason"], registry=r)
        self.webrtc_dc_too_large = Counter(
            "telesplat_webrtc_dc_too_large", "WebRTC peers closed for a data-channel message "
            "past webrtc_max_message_bytes", registry=r)
        self.webrtc_dc_inbox_dropped = Counter(
            "telesplat_webrtc_dc_inbox_dropped", "Reassembled data-channel messages dropped "
            "because the session had 64 unread", registry=r)
        self.voice_packets = Counter(
            "telesplat_voice_packets", "Opus packets of performers' voices, by outcome "
            "(forwarded: to the seat's listeners; garbage: not a valid Opus packet; too_large: "
            "past voice_max_packet_bytes; rate: past voice_max_bitrate; refused: sent by a "
            "peer that may not publish a voice; overflow: a listener's buffer was full; "
            "unmixed: left out of a room's mix past voice_mix_max_seats)",
            ["outcome"], registry=r)
        self.voice_gap_ms = Histogram(
            "telesplat_voice_gap_ms", "Time between consecutive voice packets (each starting "
            "where the last one's audio ended), by stage: in, as the seat got them; out, as "
            "each listener (a viewer's track, a mix) took them", ["stage"],
            buckets=LATENCY_BUCKETS_MS, registry=r)

        self.loop_lag_ms = Histogram(
            "telesplat_event_loop_lag_ms", "How late the event loop woke from a "
            "loop_lag_interval_s sleep (ms): time the loop was held by other work",
            buckets=LATENCY_BUCKETS_MS, registry=r)
        self.gc_pause_ms = Histogram(
            "telesplat_gc_pause_ms", "Pauses of Python's cyclic garbage collector (ms), by "
            "generation: a collection holds the GIL, so the event loop waits it out",
            ["generation"], buckets=LATENCY_BUCKETS_MS, registry=r)
        self.loop_stalls = Counter(
            "telesplat_event_loop_stalls", "Stalls past loop_stall_log_ms whose stack was "
            "logged", registry=r)

    def render_text(self) -> bytes:
        return generate_latest(self.registry)
