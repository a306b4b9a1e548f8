"""The browser viewer: the web bundle of a workspace (bundle.py), the local server (server.py)
and the WebGL2 page (static/). docs/VIEWER.md describes what it renders and how it is tested."""
