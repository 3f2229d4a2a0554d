"""``cranetwin web-preview``: the web UI on synthetic data (no database), for front-end work."""

from __future__ import annotations

import typer


def register(app: typer.Typer) -> None:
    """Add ``cranetwin web-preview``."""

    @app.command("web-preview")
    def web_preview(
        port: int = typer.Option(8765, help="TCP port."),
        host: str = typer.Option("127.0.0.1", help="Bind address."),
    ) -> None:
        """Serve the fleet and machine pages on synthetic cranes (key: viewer-key)."""
        import uvicorn

        from cranetwin.api.preview import PREVIEW_KEY, create_preview_app

        typer.echo(f"open  http://{host}:{port}/   (synthetic data, Ctrl-C stops)")
        typer.echo(f"key   {PREVIEW_KEY}   (paste it into the page's sign-in dialog once; it "
                   "becomes a session cookie, never part of a link)")
        uvicorn.run(create_preview_app(), host=host, port=port, log_level="warning",
                    ws="websockets-sansio")
