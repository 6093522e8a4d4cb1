"""The operator console in the browser (viser). ``trackmeter`` never imports this package."""

from console.app import Console
from console.server import RunningConsole, check_port_free, start_console, start_server

__all__ = ["Console", "RunningConsole", "check_port_free", "start_console", "start_server"]
