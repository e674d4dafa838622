"""``hil sweep``: parameter studies as many independent runs, on Dask.

One job per module:

- ``spec``: the sweep file (a base scenario, fixed overrides, axes) -> the list of points, every axis
  value checked against the base before anything runs;
- ``point``: one point on a worker: its scenario built from the base text and the point's inputs, one
  ``hil.exchange.run``, and a row (``hil run --json`` keys, wall time, worker, error);
- ``engine``: where points run: a ``distributed.LocalCluster`` started and stopped here (127.0.0.1,
  no dashboard, one single-threaded worker process per core), an existing cluster at an address, or
  this process serially; results come back as they finish;
- ``table``: the Parquet dataset directory, one file per finished point, written as it arrives;
- ``report``: the markdown summary and the PNG plots of the main figures against each axis;
- ``driver``: a whole sweep (resume, progress, persistence, report) on top of the others.
"""
