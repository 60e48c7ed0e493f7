"""Argoverse 2 sensor logs for omnire: the ``argoverse2`` dataparser and scene writer."""
