# bench package: `make bench` runs `python -m bench`
