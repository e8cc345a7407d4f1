"""``cell station``: the operator's web application on the cell PC.

A Starlette app (served by uvicorn, Jinja2 pages, every asset from this package) above the run library: it
starts each inspection as a child process running the same ``cell inspect`` / ``cell resume`` the terminal
runs, pauses it with SIGINT as Ctrl-C does, aborts a stopped run through the controller's state machine
(:func:`cell.inspection_run.abort_run`), and follows a run by reading its folder's journal and checkpoint,
pushed to the page by server-sent events. Modules, one job each:

- :mod:`.settings`   what the station serves and where it binds (wider than 127.0.0.1 needs a token and TLS)
- :mod:`.users`      the users file: names, roles, scrypt-hashed PINs
- :mod:`.journal`    the station's own journal (sign-ins, refusals, requests), beside the runs
- :mod:`.recipes`    the recipes offered on the start page
- :mod:`.supervisor` one child process at a time: start, pause, resume, abort; survives a station restart
- :mod:`.progress`   a run's progress from its folder: state in words, view k of n, time left
- :mod:`.verdict`    the verdict and its reasons from results/report.json
- :mod:`.thumbnail`  a view's picture (what each camera pixel measured, or why not)
- :mod:`.results`    the results database, and the runs it could not take yet (synced later)
- :mod:`.app`        the routes; :mod:`.auth` sign-in and roles; :mod:`.server` uvicorn
"""
