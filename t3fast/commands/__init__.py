"""The ``t3fast`` command line (:mod:`t3fast.commands.main`): one module per group of
sub-commands, on top of every other package; nothing below imports from here."""
