"""omnire plugin: the ``synthetic`` dataparser and the ``omnire synth`` command."""
from omnire.api import CommandSpec, DataparserSpec, lazy

SPECS = (
    DataparserSpec("synthetic", "Synthetic street scene with ground truth: generated into --data if it is not there "
                   "yet, then read with the processed-scene reader",
                   lazy("omnire_synthetic.dataparser:SyntheticDataparserConfig")),
    CommandSpec("synth", "Generate a synthetic driving scene with ground truth", lazy("omnire_synthetic.cli:main")),
)
