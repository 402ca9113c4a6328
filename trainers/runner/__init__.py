"""The frame every command runs in: options from configs, validation, the memory estimate, one
writer per ``--out``, resume, the progress bar, atomic result files and the results envelope
(``frame``), the commands' registry (``registry``), and kept work (``kept``)."""
