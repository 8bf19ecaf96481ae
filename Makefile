# microray - the one entry point.
#   make          build build/microrayd (and build/microray)
#   make test     install missing Debian packages, build, run unit + end-to-end tests
#   make check    the same tests built with AddressSanitizer + UBSan (build/check/)
#   make hard     the hard cases (tests/hard) built as make check builds them, run, and a
#                 table per kind of their figures against their tolerances, sanitizer
#                 reports and NaN/Inf per program (scripts/run-hard.sh; CI runs it)
#   make bench    print the benchmark table
#   make run      set up, build, render examples/skinned-walk.json into out/skinned-walk/
#   make schema   regenerate the kind blocks of schemas/job.schema.json
#   make openapi  rewrite the frame-stats schemas of schemas/openapi.yaml from the stats table
#   make fuzz-build  the libFuzzer harnesses of tests/fuzz (clang) into $(BUILD)/fuzz/
#   make fuzz        run each harness FUZZ_SECONDS (600) long; make fuzz-short: 60 s each
#                    (make test runs it), both re-running tests/fuzz/crashers first
#   make man      the manual pages microrayd.1 and microray.1 (from each program's usage table)
#   make install  binaries, man pages, bash completion, the systemd unit and the example jobs
#                 under $(DESTDIR)$(PREFIX) (PREFIX /usr/local); make uninstall removes them
#   make clean

BUILD   ?= build
CC      ?= cc
# -O3: the same frames bit for bit as -O2 (every example; no option here
# changes what a float operation rounds to), 3-12 % less time in the kinds'
# own loops: render jobs alternated with the -O2 binary traced the displaced
# sphere in 0.93, the dmm wuson in 0.94, the rigid svo at depth 8 / 10 in
# 0.95 / 0.93, 64 svo instances' update in 0.88 of the time; triangles 1.00.
OPT     ?= -O3
SAN     ?=
# preprocessor definitions of a special build (the fuzzing build's)
DEFS    ?=
WARN    := -Wall -Wextra -Werror -Wshadow -Wno-unused-parameter
# -ffp-contract=off: no fused multiply-adds behind our back; watertight
# intersection relies on two triangles evaluating a shared edge identically.
# -fno-tree-slp-vectorize: GCC 12.2's SLP vectorizer (on at -O2) can reuse
# the unrounded double where a (float) cast result is used again in double
# arithmetic, e.g. d = (float)(c - (float)(c + e)) comes out as -e; code
# that relies on exact float rounding must not be compiled that way.
# core/ (libmicroray) sees only its own headers: no -Iserver, so a core
# file that includes a server header does not compile.
CORE_CFLAGS := -std=c11 $(WARN) $(OPT) -g -ffp-contract=off -fno-tree-slp-vectorize -D_DEFAULT_SOURCE -Icore -I/usr/include/OpenEXR -MMD -MP $(SAN) $(DEFS)
# common/: what both programs link (the usage-table printer), nothing else.
CFLAGS  := $(CORE_CFLAGS) -Iserver -Icommon -I/usr/include/cjson
LDFLAGS := $(SAN)
CORE_LIBS   := -lassimp -lembree3 -lOpenEXRCore-3_1 -ldeflate -lmeshoptimizer -lpng16 -ljpeg -lpthread -lm
SERVER_LIBS := -lcjson -lsqlite3 -lmicrohttpd -lcurl
CLIENT_LIBS := -lcurl -lcjson
TEST_LIBS   := -lcmocka -lcurl

CORE_SRC   := $(sort $(wildcard core/*.c core/*/*.c core/*/*/*.c))
SERVER_SRC := $(filter-out server/main.c,$(sort $(wildcard server/*.c)))
CLIENT_SRC := $(sort $(wildcard client/*.c))
COMMON_SRC := $(sort $(wildcard common/*.c))
# Test programs: tests/<suite>/test_*.c -> $(BUILD)/tests/<suite>/test_*
TEST_SRC   := $(sort $(wildcard tests/unit/test_*.c tests/hard/test_*.c tests/integration/test_*.c))
HARD_SRC   := $(sort $(wildcard tests/hard/test_*.c))
BENCH_SRC  := $(sort $(wildcard bench/*.c))
# Generators of checked-in text: tools/*.c -> $(BUILD)/tools/*
TOOL_SRC   := $(sort $(wildcard tools/*.c))

obj = $(patsubst %.c,$(BUILD)/obj/%.o,$(1))
CORE_OBJ   := $(call obj,$(CORE_SRC))
SERVER_OBJ := $(call obj,$(SERVER_SRC) $(COMMON_SRC))
TEST_BIN   := $(patsubst tests/%.c,$(BUILD)/tests/%,$(TEST_SRC))
BENCH_BIN  := $(patsubst bench/%.c,$(BUILD)/bench/%,$(BENCH_SRC))
TOOL_BIN   := $(patsubst tools/%.c,$(BUILD)/tools/%,$(TOOL_SRC))
CLIENT_BIN := $(if $(CLIENT_SRC),$(BUILD)/microray)
# libFuzzer harnesses: tests/fuzz/fuzz_*.c -> $(BUILD)/fuzz/fuzz_* (docs/fuzzing.md).
# The whole tree is rebuilt for them with clang, ASan and UBSan into
# $(BUILD)/fuzz/ (a sub-make with BUILD=$(BUILD)/fuzz builds fuzz-bins).
FUZZ_CC      ?= clang
FUZZ_SECONDS ?= 600
FUZZ_SAN     := -fsanitize=address,undefined -fno-sanitize-recover=all -fno-omit-frame-pointer \
                -fsanitize=fuzzer-no-link
# libFuzzer's convention: the fuzzed build takes every checksum as matching
# (util/crc32.h), so inputs get past them to the fields they guard.
FUZZ_DEFS    := -DFUZZING_BUILD_MODE_UNSAFE_FOR_PRODUCTION
FUZZ_SRC     := $(sort $(wildcard tests/fuzz/fuzz_*.c))
FUZZ_BIN     := $(patsubst tests/fuzz/%.c,$(BUILD)/%,$(FUZZ_SRC))

.PHONY: all setup test check hard bench run clean tests schema openapi fuzz-build fuzz-bins fuzz fuzz-short \
        man install uninstall
# keep objects of test and bench programs (make would delete them as intermediates)
.SECONDARY:
all: $(BUILD)/microrayd $(CLIENT_BIN)

$(BUILD)/obj/core/%.o: core/%.c
	@mkdir -p $(dir $@)
	$(CC) $(CORE_CFLAGS) -c $< -o $@

$(BUILD)/obj/%.o: %.c
	@mkdir -p $(dir $@)
	$(CC) $(CFLAGS) -c $< -o $@

$(BUILD)/libmicroray.a: $(CORE_OBJ)
	@rm -f $@
	ar rcs $@ $^

$(BUILD)/libmicrorayd.a: $(SERVER_OBJ)
	@rm -f $@
	ar rcs $@ $^

$(BUILD)/microrayd: $(call obj,server/main.c) $(BUILD)/libmicrorayd.a $(BUILD)/libmicroray.a
	$(CC) $(LDFLAGS) -o $@ $^ $(SERVER_LIBS) $(CORE_LIBS)

$(BUILD)/microray: $(call obj,$(CLIENT_SRC) $(COMMON_SRC))
	$(CC) $(LDFLAGS) -o $@ $^ $(CLIENT_LIBS)

$(BUILD)/tests/%: $(BUILD)/obj/tests/%.o $(BUILD)/libmicrorayd.a $(BUILD)/libmicroray.a
	@mkdir -p $(dir $@)
	$(CC) $(LDFLAGS) -o $@ $^ $(TEST_LIBS) $(SERVER_LIBS) $(CORE_LIBS)

$(BUILD)/bench/%: $(BUILD)/obj/bench/%.o $(BUILD)/libmicrorayd.a $(BUILD)/libmicroray.a
	@mkdir -p $(dir $@)
	$(CC) $(LDFLAGS) -o $@ $^ $(SERVER_LIBS) $(CORE_LIBS) -lcurl

$(BUILD)/tools/%: $(BUILD)/obj/tools/%.o $(BUILD)/libmicrorayd.a $(BUILD)/libmicroray.a
	@mkdir -p $(dir $@)
	$(CC) $(LDFLAGS) -o $@ $^ $(SERVER_LIBS) $(CORE_LIBS)

$(BUILD)/fuzz_%: $(BUILD)/obj/tests/fuzz/fuzz_%.o $(BUILD)/libmicrorayd.a $(BUILD)/libmicroray.a
	$(CC) $(LDFLAGS) -fsanitize=fuzzer -o $@ $^ $(SERVER_LIBS) $(CORE_LIBS)

tests: all $(TEST_BIN) $(TOOL_BIN)

# Only in the sub-make of fuzz-build, where BUILD is the fuzz tree.
fuzz-bins: $(FUZZ_BIN)

fuzz-build:
	$(MAKE) fuzz-bins BUILD=$(BUILD)/fuzz CC=$(FUZZ_CC) OPT=-O1 SAN="$(FUZZ_SAN)" DEFS="$(FUZZ_DEFS)"

fuzz: fuzz-build
	bash scripts/run-fuzz.sh $(BUILD) $(FUZZ_SECONDS)

fuzz-short: fuzz-build
	bash scripts/run-fuzz.sh $(BUILD) 60

# The frame-stats schemas (Seconds, FrameStats) of schemas/openapi.yaml are
# generated from the field table in core/render/frame_stats.c;
# test_stats_json fails while they are stale.
openapi: $(BUILD)/tools/openapi_stats
	$(BUILD)/tools/openapi_stats schemas/openapi.yaml

setup:
	@bash scripts/setup.sh

# The fuzz run goes on after failed tests (and fails the target too).
test: setup
	$(MAKE) tests fuzz-build
	bash scripts/run-tests.sh $(BUILD); t=$$?; bash scripts/run-fuzz.sh $(BUILD) 60 || exit 1; exit $$t

# The sanitizer build of make check and make hard: the whole tree again in
# build/check/, at -O1 with AddressSanitizer (LeakSanitizer included) and
# UBSan, which stops at the first report.
CHECK_BUILD := BUILD=build/check OPT=-O1 SAN="-fsanitize=address,undefined -fno-omit-frame-pointer -fno-sanitize-recover=all"

check: setup
	$(MAKE) tests $(CHECK_BUILD)
	bash scripts/run-tests.sh build/check

hard: setup
	$(MAKE) $(patsubst tests/%.c,build/check/tests/%,$(HARD_SRC)) $(CHECK_BUILD)
	bash scripts/run-hard.sh build/check

bench: setup
	$(MAKE) all $(BENCH_BIN)
	bash scripts/run-bench.sh $(BUILD)

run: setup
	$(MAKE) all
	bash scripts/run-example.sh $(BUILD)

# The job schema's kind blocks, regenerated from the kinds' parameter tables
# (server/schema_gen.h); test_schema fails while the committed file is stale.
schema: all
	$(BUILD)/microrayd schema schemas/job.schema.json > schemas/job.schema.json.new
	mv schemas/job.schema.json.new schemas/job.schema.json

# Manual pages and bash completion, printed by the programs from the same
# tables as their --help (server/usage.c, client/usage.c).
MAN_PAGES  := $(BUILD)/man/microrayd.1 $(BUILD)/man/microray.1
COMPLETION := $(BUILD)/completion/microrayd $(BUILD)/completion/microray

man: $(MAN_PAGES)

$(BUILD)/man/%.1: $(BUILD)/%
	@mkdir -p $(dir $@)
	$< man > $@.tmp && mv $@.tmp $@

$(BUILD)/completion/%: $(BUILD)/%
	@mkdir -p $(dir $@)
	$< completion > $@.tmp && mv $@.tmp $@

PREFIX  ?= /usr/local
DESTDIR ?=
BINDIR  := $(PREFIX)/bin
MANDIR  := $(PREFIX)/share/man/man1
DATADIR := $(PREFIX)/share/microray
COMPDIR := $(PREFIX)/share/bash-completion/completions
UNITDIR ?= $(PREFIX)/lib/systemd/system

install: $(BUILD)/microrayd $(BUILD)/microray $(MAN_PAGES) $(COMPLETION)
	install -d $(DESTDIR)$(BINDIR) $(DESTDIR)$(MANDIR) $(DESTDIR)$(COMPDIR) $(DESTDIR)$(UNITDIR) \
	           $(DESTDIR)$(DATADIR)/examples $(DESTDIR)$(DATADIR)/examples/models
	install -m 755 $(BUILD)/microrayd $(BUILD)/microray $(DESTDIR)$(BINDIR)/
	install -m 644 $(MAN_PAGES) $(DESTDIR)$(MANDIR)/
	install -m 644 $(COMPLETION) $(DESTDIR)$(COMPDIR)/
	sed -e 's|@BINDIR@|$(BINDIR)|g' -e 's|@DATADIR@|$(DATADIR)|g' packaging/microrayd.service.in \
	    > $(DESTDIR)$(UNITDIR)/microrayd.service
	chmod 644 $(DESTDIR)$(UNITDIR)/microrayd.service
	install -m 644 packaging/microrayd.default $(DESTDIR)$(DATADIR)/microrayd.default
	install -m 644 examples/*.json $(DESTDIR)$(DATADIR)/examples/
	install -m 644 examples/models/*.obj $(DESTDIR)$(DATADIR)/examples/models/

uninstall:
	rm -f $(DESTDIR)$(BINDIR)/microrayd $(DESTDIR)$(BINDIR)/microray \
	      $(DESTDIR)$(MANDIR)/microrayd.1 $(DESTDIR)$(MANDIR)/microray.1 \
	      $(DESTDIR)$(COMPDIR)/microrayd $(DESTDIR)$(COMPDIR)/microray \
	      $(DESTDIR)$(UNITDIR)/microrayd.service
	rm -rf $(DESTDIR)$(DATADIR)

clean:
	rm -rf build out

-include $(shell find $(BUILD)/obj -name '*.d' 2>/dev/null)
