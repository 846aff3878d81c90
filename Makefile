# colf — build, test, demo, man pages, install.
# Everything builds in release mode: candle in debug is ~200x slower, and one profile keeps one
# build cache.

PREFIX ?= /usr/local
CARGO ?= cargo
RELEASE := target/release
BINS := $(patsubst bin/%.rs,%,$(wildcard bin/colf-*.rs))
DEMO := out/demo

.PHONY: all build test lint man demo install uninstall clean

all: build

build:
	$(CARGO) build --release

# The test command of the README and of .ci/run.
test:
	$(CARGO) test --release

lint:
	$(CARGO) fmt --check
	$(CARGO) clippy --release --all-targets -- -D warnings

# Regenerate man/*.1 from the clap definitions, then check that groff renders them cleanly.
man:
	COLF_UPDATE_MAN=1 $(CARGO) test --release --test man_pages
	@for page in man/*.1; do \
	  out=$$(groff -man -ww -z $$page 2>&1); \
	  if [ -n "$$out" ]; then echo "$$page: $$out"; exit 1; fi; \
	done
	@echo "man pages: $(words $(wildcard man/*.1)) rendered without warnings"

# synthesise a scene, encode one view, move one object and delete another, render an orbit
# with masks, and draw a contact sheet.
demo: build
	@mkdir -p $(DEMO)
	$(RELEASE)/colf-synth --out $(DEMO)/data --scenes 1 --seed 7 --split test
	$(RELEASE)/colf-encode $(DEMO)/data/scene_00000/view_000.png \
	  --camera $(DEMO)/data/scene_00000/transforms.json -o $(DEMO)/scene.codes
	$(RELEASE)/colf-edit --inspect $(DEMO)/scene.codes > $(DEMO)/slots.json
	$(RELEASE)/colf-edit examples/demo-edits.json $(DEMO)/scene.codes -o $(DEMO)/edited.codes
	$(RELEASE)/colf-cameras orbit --frames 8 --size 64 -o $(DEMO)/orbit.json
	$(RELEASE)/colf-render $(DEMO)/scene.codes --cameras $(DEMO)/orbit.json --out $(DEMO)/orbit --masks
	$(RELEASE)/colf-render $(DEMO)/edited.codes --cameras $(DEMO)/orbit.json --out $(DEMO)/edited --masks
	@echo "demo: renders in $(DEMO)/orbit and $(DEMO)/edited"

install: build
	install -d $(DESTDIR)$(PREFIX)/bin $(DESTDIR)$(PREFIX)/share/man/man1
	install -m 755 $(addprefix $(RELEASE)/,$(BINS)) $(DESTDIR)$(PREFIX)/bin/
	install -m 644 man/*.1 $(DESTDIR)$(PREFIX)/share/man/man1/

uninstall:
	rm -f $(addprefix $(DESTDIR)$(PREFIX)/bin/,$(BINS))
	rm -f $(addprefix $(DESTDIR)$(PREFIX)/share/man/man1/,$(notdir $(wildcard man/*.1)))

clean:
	$(CARGO) clean
	rm -rf out
