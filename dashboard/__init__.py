"""busgate's fleet dashboard: one web page of every gateway on the zenoh network, live.

The rooms: ``fleet`` (what is known of the fleet, and what changed), ``feed`` (one
``busgate.client`` session filling it), ``hub`` (pushing it to the browsers as Server-Sent
Events), ``app`` (the Starlette routes and the checks on what a browser may ask), ``server``
(put together and served by uvicorn), and ``static/`` (the page, its script, and the vendored
uPlot: ``static/vendor/README.md``). ``busgate dashboard`` and ``busgate demo`` serve it.
"""
