"""The picking viewer (viser: ``server``, its access ``guard``, ``images``, ``picks``) and the rerun stream
(``rerun_log``). ``guard.ssh_hint(port)`` is the SSH tunnel line. Nothing is imported here: ``fieldtool view``
registers its subcommand from ``commands`` without loading viser."""
