"""Applications on top of the library: the ``aasoatt`` command line and the paper's reproduction."""
