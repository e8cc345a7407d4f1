"""Serve the station with uvicorn: on 127.0.0.1 by default; beyond it only with a token and TLS
(:func:`cell.station.settings.check_settings`)."""

from __future__ import annotations

from cell.station.settings import StationSettings, check_settings


def serve(settings: StationSettings) -> None:
    """Check the settings, then serve until interrupted (Ctrl-C stops the station; a run it started goes on
    in its own process, and a restarted station follows it again)."""
    import uvicorn

    from cell.station.app import create_app

    check_settings(settings)
    settings.state_dir.mkdir(parents=True, exist_ok=True)
    uvicorn.run(
        create_app(settings),
        host=settings.host,
        port=settings.port,
        ssl_certfile=str(settings.tls_cert) if settings.tls_cert else None,
        ssl_keyfile=str(settings.tls_key) if settings.tls_key else None,
        log_level="warning",
        timeout_graceful_shutdown=3,  # live pages keep event streams open: do not wait for them long
    )
