"""``omnire batch``: run many ``omnire train`` jobs (scenes x methods x variants x seeds) as
Ray tasks on one machine or a Ray cluster, skip finished jobs and resume interrupted ones on
a rerun, and gather the results like ``omnire bench train`` (JSON, markdown tables, plots)."""

__version__ = "0.1.0"
