"""difareli-app: a local web page to relight a face photo or a store record.

``service`` (sources, target lights, relights, caches; no HTTP), ``envmaps`` (small procedural HDR maps),
``server`` (standard-library HTTP server + the JSON API), ``static/index.html`` (the page: drop zone, light
sphere, HDR map and rotation, shadow strength, sampler and steps, the relit photo with its seconds and the
model's reconstruction error).
"""
