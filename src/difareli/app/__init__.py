"""difareli-app: a local web page to relight a face photo or a store record: ``service`` (sources, target
lights, relights, caches; no HTTP), ``server`` (standard-library HTTP server + the JSON API), ``checks`` (what a
request may hold), ``cache``, ``examples``, ``presets`` and ``static/index.html`` (the page)."""
