"""`mine view`: browse a catalogue in a web browser — a gallery of tubes and a page per tube.

``server.py`` serves it (standard library only), ``catalogue.py`` asks the catalogue,
``filters.py`` turns the gallery's filter into bound SQL, ``images.py`` draws the masks on the
source frames; ``static/`` holds the pages (plain HTML, JS and CSS, shipped as package data).
"""
