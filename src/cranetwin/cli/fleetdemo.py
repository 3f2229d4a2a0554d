"""``cranetwin fleetdemo``: ingest daemon + API + twin worker + simulated cranes, one Ctrl-C stops
all."""

from __future__ import annotations

import logging
import signal
import time

import typer


def register(app: typer.Typer) -> None:
    """Add ``cranetwin fleetdemo``."""

    @app.command("fleetdemo")
    def fleetdemo(
        machines: int = typer.Option(3, min=1, max=50, help="Number of simulated cranes."),
        port: int = typer.Option(8000, min=1, max=65535, help="TCP port of the API and web UI."),
        udp_port: int = typer.Option(5005, min=1, max=65535,
                                     help="UDP port of the ingest daemon."),
        host: str = typer.Option("127.0.0.1", help="Bind address of the API."),
        db: str = typer.Option("sqlite:///cranetwin-demo.db",
                               help="Database URL; an existing demo database is continued, "
                               "never deleted (delete the file for a fresh start)."),
        speed: float = typer.Option(1.0, min=0.1, max=20.0, help="Simulation speed [× real "
                                    "time]."),
        attach: bool = typer.Option(False, help="Only register cranes and stream, to a service "
                                    "and daemon that run elsewhere (docker-compose)."),
        api: str | None = typer.Option(None, help="API base URL when attached."),
        ingest: str | None = typer.Option(None, help="Daemon host:port when attached."),
        public_url: str | None = typer.Option(None, help="Base URL to print for the browser."),
        sim_hours: float = typer.Option(24.0, min=0.01, max=168.0, help="Simulated work per "
                                        "crane [h], continuous log-loading cycles (the cranes "
                                        "hold still after it)."),
        start_timeout: float = typer.Option(600.0, min=5.0, help="Longest wait for the API to "
                                            "start [s] (the wait reports what it waits for)."),
    ) -> None:
        """Run the demo: daemon and service on SQLite, cranes streaming log-loading cycles
        over UDP. Prints the URL to open and a key to sign in with; Ctrl-C stops everything."""
        from cranetwin.demo import DemoConfig, DemoError, FleetDemo

        logging.basicConfig(level=logging.INFO, format="%(message)s")
        t0 = time.monotonic()

        def _terminate(signum: int, frame: object) -> None:  # docker stop, timeout, kill
            raise KeyboardInterrupt

        signal.signal(signal.SIGTERM, _terminate)
        # Ctrl-C even when started from a shell that ignores SIGINT in background jobs
        signal.signal(signal.SIGINT, signal.default_int_handler)
        config = DemoConfig(machines=machines, db_url=None if attach and db.startswith(
            "sqlite:///cranetwin-demo") else db, host=host, port=port, udp_port=udp_port,
            speed=speed, attach=attach, api_url=api, ingest_addr=ingest, public_url=public_url,
            scenario_s=sim_hours * 3600.0, start_timeout_s=start_timeout)

        def _progress(text: str) -> None:
            typer.echo(f"[{time.monotonic() - t0:5.1f} s] {text}")

        demo = FleetDemo(config, progress=_progress)
        try:
            url = demo.start()
            typer.echo("")
            typer.echo(f"cranetwin demo running: {machines} crane(s) streaming over UDP to "
                       f"{config.ingest}; logs in {demo.logdir}/")
            typer.echo(f"open  {url}")
            typer.echo(f"key   {demo.browser_key}   (role fleet; paste it into the page's "
                       "sign-in dialog once)")
            typer.echo("Ctrl-C stops everything.")
            demo.watch(t0)
        except KeyboardInterrupt:
            typer.echo("\nstopping: cranes, ingest daemon, twin worker, API …")
        except DemoError as exc:
            typer.echo(f"error: {exc}", err=True)
            demo.stop()
            raise typer.Exit(2) from exc
        demo.stop()
        typer.echo("stopped.")
