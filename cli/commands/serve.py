"""`macroloc serve --config FILE`: the long-running localization service on Zenoh."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command()
    def serve(
        config: Path = typer.Option(None, "--config", "-c", help="Config file (JSON or TOML); see dump-config."),
        building: Path = typer.Option(None, "--building", help="IFC or mesh of the building (service.building)."),
        vehicle: str = typer.Option(None, "--vehicle", help="Vehicle name: keys macroloc/<vehicle>/..."),
        connect: list[str] = typer.Option(None, "--connect", help="Zenoh endpoint to connect to (repeatable)."),
        listen: list[str] = typer.Option(None, "--listen", help="Zenoh endpoint to listen on (repeatable)."),
        mode: str = typer.Option(None, "--mode", help="Zenoh mode: peer (default), client or router."),
        state_dir: Path = typer.Option(None, "--state-dir", help="Where the map is saved (service.state_dir)."),
        log_json: bool = typer.Option(False, "--log-json", help="Structured logs: one JSON object per line."),
        ros: bool = typer.Option(False, "--ros", help="Also ROS 2 (CDR) on the keys zenoh-bridge-ros2dds maps to "
                                 "/<vehicle>/macroloc/{pose,odometry,path,status,goal} and /tf (ros.enabled)."),
        px4: bool = typer.Option(False, "--px4", help="Also PX4's fmu/in/ topics (px4.enabled)."),
        foxglove: int = typer.Option(None, "--foxglove", help="Serve the operator's live view: Foxglove's WebSocket "
                                     "server on this port (foxglove.port; bound to foxglove.host, 127.0.0.1 by "
                                     "default; layout docs/foxglove_layout.json)."),
    ) -> None:
        """Serve poses and waypoints over Zenoh: subscribe macroloc/<vehicle>/{stereo,imu,odometry,observations,goal},
        publish {pose,waypoints,features,diagnostics,status}, answer queries on {map,plan}, hold the liveliness
        token macroloc/<vehicle>/alive. SIGTERM drains, saves the map and stops cleanly.
        """
        import logging

        from macroloc.service.config import load_config
        from macroloc.service.logs import configure_logging
        from macroloc.service.serve import serve as run

        overrides: dict[str, dict] = {"service": {}, "zenoh": {}, "ros": {}, "px4": {}, "foxglove": {}}
        for section, key, value in (("service", "building", building), ("service", "vehicle", vehicle),
                                    ("service", "state_dir", state_dir), ("zenoh", "connect", connect),
                                    ("zenoh", "listen", listen), ("zenoh", "mode", mode)):
            if value:
                overrides[section][key] = value
        if log_json:
            overrides["service"]["log_json"] = True
        if ros:
            overrides["ros"]["enabled"] = True
        if px4:
            overrides["px4"]["enabled"] = True
        if foxglove is not None:
            overrides["foxglove"]["port"] = foxglove
        cfg = load_config(config, **overrides)
        configure_logging(logging.INFO, cfg.service.log_json)
        run(cfg)
